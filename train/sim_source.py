"""Source kind ``sim``: single frames rendered by the synthetic data engine (``evtrack.sim``).

Each sample shows the object (a mesh file, a YCB name or a procedural ``box``/``can``/
``bottle``, resolved by :func:`evtrack.sim.objects.resolve_object`, in its bounding-box-centred
frame) at a random pose in front of a randomised scene (background texture, light, static
distractor objects: :func:`evtrack.sim.scene.build_scene` with ``randomize``), optionally
motion-blurred by averaging renders along a random constant twist over the exposure (the
ground-truth pose is the one at mid-exposure, as for the engine's 60 FPS frames), with the
engine's sensor noise, encoded to 8-bit sRGB.

Consecutive samples share a scene (``samples_per_scene``): building a scene uploads its
textures to the GPU, which costs far more than rendering, so the source keeps the current
scene's renderer and is fastest read in order; use ``data.cache_dir`` to render once into
shards and train from those.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal

import numpy as np

from evtrack.configs import Config, FieldError, setting
from evtrack.errors import ConfigError
from evtrack.models.cuboid import Cuboid
from evtrack.train.samples import PoseSample, SourceSpec, project_keypoints, register_source

__all__ = ["SimSourceOptions", "SimSource", "sim_object_cuboid"]

_CUBOID_TOLERANCE_M = 1e-4  # the config's cuboid and the engine's mesh must agree this well


DistractorKind = Literal["box", "can", "bottle"]
"""A procedural kind of distractor object of the synthetic data engine."""


@dataclass(frozen=True)
class SimSourceOptions(Config):
    """Options of the ``sim`` source (``data.options`` of a config).

    Attributes:
        samples_per_scene: consecutive samples sharing one random scene.
        object_seed: texture seed of procedural objects.
        focal_at_640: focal length in pixels for a 640-pixel-wide image (scaled to the
            configured width; 615 is the engine's default camera).
        z_range: depth range of the object centre, metres.
        margin: fraction of the image size kept between the object centre and the border.
        max_distractors: most static distractor objects per scene.
        distractor_kinds: procedural kinds of the distractors; ``None`` (default): all of
            ``box``, ``can``, ``bottle`` but the object's own kind when the object is one of
            them — a look-alike box next to the box to learn makes its corners ambiguous
            (the network then marks every box's corners).
        blur_probability: probability that a sample is motion-blurred.
        blur_renders: renders averaged over the exposure of a blurred sample.
        exposure_s: exposure time, seconds.
        max_linear_speed: largest object speed during a blurred exposure, m/s.
        max_angular_speed: largest angular speed during a blurred exposure, rad/s.
        ambient_range, diffuse_range: per-sample light strengths.
        view_directions: object-frame directions from the object towards the camera (any
            length) around which ``view_probability`` of the samples are drawn, e.g. the views
            a network gets wrong; the others (and all without it) have a uniformly random
            rotation.
        view_probability: share of the samples drawn around ``view_directions`` (one of them
            at random, then Gaussian noise of ``view_spread_deg`` per axis on the direction and
            a uniformly random roll about the line of sight).
        view_spread_deg: see ``view_probability``.
    """

    samples_per_scene: int = setting(32, ge=1)
    object_seed: int = 0
    focal_at_640: float = setting(615.0, unit="px")
    z_range: tuple[float, float] = setting((0.35, 1.2), gt=0, unit="m")
    margin: float = setting(0.1, ge=0, lt=0.5)
    max_distractors: int = 4
    distractor_kinds: tuple[DistractorKind, ...] | None = None
    blur_probability: float = setting(0.5, ge=0, le=1)
    blur_renders: int = setting(8, ge=1)
    exposure_s: float = setting(1.0 / 60.0, unit="s")
    max_linear_speed: float = setting(1.5, unit="m/s")
    max_angular_speed: float = setting(8.0, unit="rad/s")
    ambient_range: tuple[float, float] = (0.15, 0.5)
    diffuse_range: tuple[float, float] = (0.4, 0.9)
    view_directions: tuple[tuple[float, float, float], ...] | None = None
    view_probability: float = setting(0.0, ge=0, le=1)
    view_spread_deg: float = setting(20.0, ge=0, unit="deg")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.view_directions is not None:
            object.__setattr__(self, "view_directions", self._checked_directions())
        if self.view_probability > 0 and not self.view_directions:
            raise FieldError(self, "view_probability", f"is {self.view_probability}, which "
                             "needs view_directions")
        lo, hi = self.z_range
        if not lo <= hi:
            raise FieldError(self, "z_range", f"must be 0 < low <= high, got {self.z_range}")

    def _checked_directions(self) -> tuple[tuple[float, float, float], ...]:
        """``view_directions`` as a tuple of ``(x, y, z)`` float triples.

        Raises:
            FieldError: not a list of non-zero finite ``[x, y, z]`` directions.
        """
        try:
            dirs = np.asarray(self.view_directions, np.float64).reshape(-1, 3)
        except (TypeError, ValueError):
            raise FieldError(self, "view_directions", "must be a list of [x, y, z] "
                             f"directions, got {self.view_directions!r}") from None
        if not len(dirs) or not np.isfinite(dirs).all() or (
                np.linalg.norm(dirs, axis=1) == 0).any():
            raise FieldError(self, "view_directions", "must be non-zero finite [x, y, z] "
                             f"directions, got {self.view_directions!r}")
        return tuple((float(x), float(y), float(z)) for x, y, z in dirs)


def _resolve(spec: str, seed: int):
    from evtrack.sim.objects import resolve_object

    return resolve_object(spec, seed=seed)


def sim_object_cuboid(spec: str, seed: int = 0) -> Cuboid:
    """The cuboid of an engine object (mesh path, YCB or procedural name) in the engine's
    object frame (bounding-box centred)."""
    mesh = _resolve(spec, seed)
    lo, hi = mesh.vertices.min(0).astype(np.float64), mesh.vertices.max(0).astype(np.float64)
    return Cuboid(tuple(hi - lo), tuple((hi + lo) / 2))


def _exp_twist(twist: np.ndarray, dt: float) -> np.ndarray:
    """(4, 4) motion of a constant camera-frame twist ``[v, ω]`` over ``dt`` seconds."""
    import torch

    from evtrack.geometry import integrate_twist

    T = integrate_twist(torch.eye(4, dtype=torch.float64), torch.from_numpy(twist), dt)
    return T.numpy()


class SimSource:
    """Rendered samples of one object (see the module docstring).

    Args:
        object_spec: mesh path, YCB name or procedural name.
        cuboid: the object's cuboid; must match the engine's mesh (bounding-box centred).
        num_samples, image_size, seed: as for every source.
        object_name: name recorded with the samples.
        options: rendering and randomisation options.
    """

    def __init__(
        self,
        object_spec: str,
        cuboid: Cuboid,
        num_samples: int,
        image_size: tuple[int, int],
        *,
        object_name: str,
        seed: int = 0,
        options: SimSourceOptions | None = None,
    ) -> None:
        from evtrack.camera import PinholeCamera

        self.options = options or SimSourceOptions()
        self.object_spec = object_spec
        self.object_name = object_name
        self.num_samples = int(num_samples)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.seed = int(seed)
        engine_cuboid = sim_object_cuboid(object_spec, self.options.object_seed)
        if (np.abs(np.subtract(engine_cuboid.dimensions, cuboid.dimensions)).max()
                > _CUBOID_TOLERANCE_M
                or np.abs(np.subtract(engine_cuboid.center, cuboid.center)).max()
                > _CUBOID_TOLERANCE_M):
            raise ConfigError(
                f"object {object_spec!r}: the configured cuboid {cuboid.to_dict()} differs from "
                f"the engine's mesh {engine_cuboid.to_dict()} (the engine centres meshes on "
                "their bounding box: keep object.recenter true, or give no dimensions)")
        self.cuboid = cuboid
        h, w = self.image_size
        f = self.options.focal_at_640 * w / 640.0
        self.camera = PinholeCamera(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
        self.K = self.camera.K().numpy()
        o = self.options
        self.description = (
            f"{self.num_samples} evtrack.sim renders {w}x{h} of {object_spec!r} (seed {seed}, "
            f"{o.samples_per_scene} per random scene, up to {o.max_distractors} distractors, "
            f"z {o.z_range[0]}-{o.z_range[1]} m, blur p={o.blur_probability} up to "
            f"{o.max_linear_speed} m/s and {o.max_angular_speed} rad/s over {o.exposure_s:.4f} s"
            + (f"; {o.view_probability:g} of the rotations around the views "
               f"{[list(d) for d in o.view_directions]} (object frame), "
               f"{o.view_spread_deg:g} deg spread" if o.view_probability > 0 else "")
            + ")"
        )
        self._mesh = None
        self._renderer = None
        self._scene_index = -1
        self._pid = -1

    def __len__(self) -> int:
        return self.num_samples

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()  # GL objects stay in the process that made them
        state.update(_mesh=None, _renderer=None, _scene_index=-1, _pid=-1)
        return state

    def _distractor_kinds(self) -> tuple[str, ...]:
        """The distractor kinds (see :attr:`SimSourceOptions.distractor_kinds`)."""
        if self.options.distractor_kinds is not None:
            return tuple(self.options.distractor_kinds)
        own = self.object_spec.split(":")[0].lower()
        return tuple(k for k in ("box", "can", "bottle") if k != own)

    def close(self) -> None:
        """Release the current renderer (its GL context)."""
        if self._renderer is not None and self._pid == os.getpid():
            self._renderer.release()
        self._renderer, self._scene_index = None, -1

    def _renderer_for(self, scene_index: int):
        from evtrack.sim.config import SceneConfig
        from evtrack.sim.renderer import Renderer
        from evtrack.sim.scene import build_scene

        if self._pid != os.getpid():  # a (forked) worker: its own mesh and GL context
            self._renderer, self._mesh, self._scene_index, self._pid = None, None, -1, os.getpid()
        if self._mesh is None:
            self._mesh = _resolve(self.object_spec, self.options.object_seed)
        if scene_index != self._scene_index:
            self.close()
            rng = np.random.default_rng([self.seed, scene_index])
            scene = build_scene(
                SceneConfig(randomize=True, max_distractors=self.options.max_distractors,
                            distractor_kinds=self._distractor_kinds()),
                self.camera, rng)
            renderer = Renderer(self.camera)
            scene.apply(renderer)
            renderer.set_object(self._mesh)
            self._renderer, self._scene_index = renderer, scene_index
        return self._renderer

    def _random_pose(self, rng: np.random.Generator) -> np.ndarray:
        from evtrack.sim.trajectory import random_rotation

        h, w = self.image_size
        o = self.options
        z = rng.uniform(*o.z_range)
        u = rng.uniform(o.margin * w, (1 - o.margin) * w)
        v = rng.uniform(o.margin * h, (1 - o.margin) * h)
        T = np.eye(4)
        centre = np.linalg.solve(self.K, np.array([u, v, 1.0])) * z
        if o.view_probability > 0 and rng.random() < o.view_probability:
            T[:3, :3] = self._rotation_towards_view(rng, -centre / np.linalg.norm(centre))
        else:
            T[:3, :3] = random_rotation(rng)
        T[:3, 3] = centre - T[:3, :3] @ np.asarray(self.cuboid.center)
        return T

    def _rotation_towards_view(self, rng: np.random.Generator, to_camera: np.ndarray
                               ) -> np.ndarray:
        """(3, 3) object-to-camera rotation that puts one of the options' view directions
        (with noise, object frame) on ``to_camera`` (camera frame, unit: from the object's
        centre towards the camera), with a uniformly random roll about it."""
        from scipy.spatial.transform import Rotation

        o = self.options
        dirs = np.asarray(o.view_directions, np.float64)
        d = dirs[rng.integers(len(dirs))]
        d = d / np.linalg.norm(d) + rng.standard_normal(3) * np.radians(o.view_spread_deg)
        d /= np.linalg.norm(d)
        align, _ = Rotation.align_vectors(to_camera[None], d[None])
        roll = Rotation.from_rotvec(to_camera * rng.uniform(-np.pi, np.pi))
        return (roll * align).as_matrix()

    def __getitem__(self, index: int) -> PoseSample:
        from evtrack.sim.config import FrameConfig
        from evtrack.sim.frames import add_rgb_noise, linear_to_srgb

        if not 0 <= index < self.num_samples:
            raise IndexError(f"sample {index} out of range 0..{self.num_samples - 1}")
        o = self.options
        renderer = self._renderer_for(index // o.samples_per_scene)
        rng = np.random.default_rng([self.seed, index // o.samples_per_scene, index])
        light = rng.standard_normal(3)
        light[2] = -abs(light[2]) - 0.3  # from the camera's side
        renderer.set_light(light, rng.uniform(*o.ambient_range), rng.uniform(*o.diffuse_range))
        pose = self._random_pose(rng)
        if rng.random() < o.blur_probability:
            direction = rng.standard_normal(6)
            twist = np.concatenate([
                direction[:3] / np.linalg.norm(direction[:3]) * rng.uniform(0, o.max_linear_speed),
                direction[3:] / np.linalg.norm(direction[3:]) * rng.uniform(0, o.max_angular_speed),
            ])
            offsets = ((np.arange(o.blur_renders) + 0.5) / o.blur_renders - 0.5) * o.exposure_s
            linear = np.mean([renderer.render(_exp_twist(twist, dt) @ pose).rgb
                              for dt in offsets], axis=0)
        else:
            linear = renderer.render(pose).rgb
        image = linear_to_srgb(add_rgb_noise(linear.astype(np.float32), rng, FrameConfig()))
        poses = pose[None]
        return PoseSample(image=image, K=self.K.copy(), poses=poses,
                          keypoints=project_keypoints(self.cuboid, poses, self.K))


@register_source("sim")
def _sim_factory(spec: SourceSpec) -> SimSource:
    return SimSource(
        spec.mesh or spec.object_name, spec.cuboid, spec.num_samples, spec.image_size,
        object_name=spec.object_name, seed=spec.seed,
        options=SimSourceOptions.from_dict(spec.options, spec.options_key),
    )
