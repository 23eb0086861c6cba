"""The static scene around the object: a textured background plane, light, distractors.

The camera is static, so nothing here produces events; it gives the RGB-D frames a realistic
background and the event stream realistic occlusion edges. For training data
(``SceneConfig.randomize``) the background texture, its brightness and contrast, the light and
a few static distractor objects are drawn at random from the scene's generator.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.sim import textures
from evtrack.sim.config import SceneConfig
from evtrack.sim.objects import ObjectMesh, make_bottle, make_box, make_can
from evtrack.sim.renderer import Renderer
from evtrack.sim.trajectory import random_rotation

__all__ = ["Scene", "StaticPart", "build_scene", "background_plane"]

_BACKGROUND_TEXTURE_WIDTH = 1024
_FRUSTUM_MARGIN = 1.1  # the background plane overfills the view by 10 %


@dataclass
class StaticPart:
    """A static mesh at a fixed object->camera pose; ``lit=False`` shows it unshaded."""

    mesh: ObjectMesh
    pose: np.ndarray
    lit: bool = True


@dataclass
class Scene:
    """Light and static parts of a scene (see :func:`build_scene`)."""

    light_direction: tuple[float, float, float]
    ambient: float
    diffuse: float
    parts: list[StaticPart] = field(default_factory=list)

    def apply(self, renderer: Renderer) -> None:
        """Set the light and add the static parts to ``renderer``."""
        renderer.set_light(self.light_direction, self.ambient, self.diffuse)
        for part in self.parts:
            renderer.add_static(part.mesh, part.pose, lit=part.lit)

    def describe(self) -> dict:
        """Plain description for metadata."""
        return {
            "light_direction": [float(v) for v in self.light_direction],
            "ambient": self.ambient,
            "diffuse": self.diffuse,
            "parts": [{"name": p.mesh.name, "source": p.mesh.source,
                       "pose": np.asarray(p.pose).tolist(), "lit": p.lit} for p in self.parts],
        }


def background_plane(camera: PinholeCamera, depth: float, texture: np.ndarray,
                     brightness: float) -> StaticPart:
    """A textured rectangle at ``z = depth`` facing the camera, filling the whole view."""
    half_w = _FRUSTUM_MARGIN * max(camera.cx + 0.5, camera.width - camera.cx - 0.5) / camera.fx
    half_h = _FRUSTUM_MARGIN * max(camera.cy + 0.5, camera.height - camera.cy - 0.5) / camera.fy
    x, y = half_w * depth, half_h * depth
    vertices = np.array([[-x, y, depth], [x, y, depth], [x, -y, depth], [-x, -y, depth]],
                        np.float32)
    # camera +y is down: vertex 0 is the bottom-left corner, uv (0, 0) the image's bottom-left
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    mesh = ObjectMesh(
        name="background",
        vertices=vertices,
        faces=np.array([[0, 1, 2], [0, 2, 3]], np.int32),
        normals=np.tile(np.array([0, 0, -1], np.float32), (4, 1)),
        uv=uv,
        texture=texture,
        colors=np.full((4, 3), brightness, np.float32),
        source="procedural:background",
    )
    return StaticPart(mesh, np.eye(4), lit=False)


def build_scene(config: SceneConfig, camera: PinholeCamera, rng: np.random.Generator) -> Scene:
    """The background, light and (for ``randomize``) distractors of one sequence.

    Args:
        config: scene settings.
        camera: the camera (the background fills its view).
        rng: the scene's generator (the same state gives the same scene).
    """
    light = config.light_direction
    ambient, diffuse = config.ambient, config.diffuse
    brightness, contrast = config.background_brightness, config.background_contrast
    if config.randomize:
        d = rng.standard_normal(3)
        d[2] = -abs(d[2]) - 0.3  # light from the camera's side
        light = tuple(float(v) for v in d / np.linalg.norm(d))
        ambient = float(rng.uniform(0.15, 0.5))
        diffuse = float(rng.uniform(0.4, 0.9))
        brightness = float(rng.uniform(0.25, 0.8))
        contrast = float(rng.uniform(0.15, 0.6))
    tex_h = max(8, int(round(_BACKGROUND_TEXTURE_WIDTH * camera.height / camera.width)))
    texture = textures.background_texture(rng, _BACKGROUND_TEXTURE_WIDTH, tex_h, contrast)
    parts = [background_plane(camera, config.background_depth, texture, brightness)]
    if config.randomize and config.max_distractors > 0 and config.distractor_kinds:
        by_kind = {"box": make_box, "can": make_can, "bottle": make_bottle}
        unknown = sorted(set(config.distractor_kinds) - set(by_kind))
        if unknown:
            raise ConfigError(f"scene.distractor_kinds: unknown kind(s) {unknown}; known: "
                              f"{sorted(by_kind)}")
        makers = tuple(by_kind[k] for k in config.distractor_kinds)
        for k in range(int(rng.integers(0, config.max_distractors + 1))):
            maker = makers[int(rng.integers(0, len(makers)))]
            mesh = maker(seed=int(rng.integers(0, 2 ** 31)), name=f"distractor{k}")
            scale = float(rng.uniform(0.6, 1.4))
            mesh = _scaled(mesh, scale)
            z = rng.uniform(*config.distractor_depth)
            u = rng.uniform(0, camera.width - 1)
            v = rng.uniform(0, camera.height - 1)
            pose = np.eye(4)
            pose[:3, :3] = random_rotation(rng)
            pose[:3, 3] = [(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z]
            parts.append(StaticPart(mesh, pose, lit=True))
    return Scene(light, ambient, diffuse, parts)


def _scaled(mesh: ObjectMesh, s: float) -> ObjectMesh:
    return ObjectMesh(mesh.name, mesh.vertices * np.float32(s), mesh.faces, mesh.normals,
                      mesh.uv, mesh.texture, mesh.colors, f"{mesh.source}:scale={s:.3f}",
                      mesh.offset)
