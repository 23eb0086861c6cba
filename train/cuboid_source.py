"""A renderer-free source: textured cuboids drawn with OpenCV at known poses.

Each visible face of the object's cuboid is a procedurally textured square (fixed per object
by ``texture_seed``: each face gets its own colour and pattern, so the box's orientation is
unambiguous) mapped with a homography, shaded by a random directional light, over random
backgrounds with distractor shapes and distractor boxes of other textures. It needs no OpenGL,
so it serves tests, quick experiments and CPU-only training of box-like demo objects; meshes
with other shapes need the synthetic data engine (source kind ``sim``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from evtrack.configs import Config, FieldError, setting
from evtrack.errors import ConfigError
from evtrack.models.cuboid import Cuboid
from evtrack.train.samples import PoseSample, SourceSpec, project_keypoints, register_source

__all__ = [
    "CuboidSourceOptions",
    "SyntheticCuboidSource",
    "draw_textured_cuboid",
    "make_face_textures",
    "FACES",
]

# corner indices of each face (see evtrack.models.cuboid for the order), as a cycle, and the
# face's outward normal as (axis, sign)
FACES: tuple[tuple[tuple[int, int, int, int], int, int], ...] = (
    ((0, 1, 3, 2), 0, -1),
    ((4, 6, 7, 5), 0, +1),
    ((0, 4, 5, 1), 1, -1),
    ((2, 3, 7, 6), 1, +1),
    ((0, 2, 6, 4), 2, -1),
    ((1, 5, 7, 3), 2, +1),
)
_TEXTURE_SIZE = 128  # pixels per side of a face texture
_DISTRACTOR_POOL = 32  # distinct random appearances of distractor boxes
_SUBPIXEL_BITS = 4  # fixed-point fraction bits of OpenCV's polygon filling
_SUBPIXEL = 1 << _SUBPIXEL_BITS


@dataclass(frozen=True)
class CuboidSourceOptions(Config):
    """Options of the ``cuboid`` source (the ``data.options`` mapping of a config).

    Attributes:
        hfov_deg: horizontal field of view of the virtual pinhole camera, degrees.
        distance_range: range of the object's depth, in multiples of its cuboid diameter.
        margin: fraction of the image size kept free between the centroid and the border.
        max_instances: instances per image are drawn uniformly from 1..max_instances.
        empty_probability: probability of an image without the object.
        texture_seed: seed of the object's face textures (its appearance).
        distractor_boxes: at most this many boxes with random textures per image.
        distractor_shapes: at most this many random 2-D shapes on the background.
        ambient: ambient part of the face shading (the rest is Lambertian).
    """

    hfov_deg: float = setting(60.0, gt=0, lt=170, unit="deg")
    distance_range: tuple[float, float] = setting((2.5, 6.0), gt=0)
    margin: float = setting(0.1, ge=0, lt=0.5)
    max_instances: int = setting(1, ge=1)
    empty_probability: float = setting(0.05, ge=0, le=1)
    texture_seed: int = 0
    distractor_boxes: int = 2
    distractor_shapes: int = 8
    ambient: float = 0.45

    def __post_init__(self) -> None:
        super().__post_init__()
        lo, hi = self.distance_range
        if not lo <= hi:
            raise FieldError(self, "distance_range", f"must be 0 < low <= high, got "
                             f"{self.distance_range}")


def make_face_textures(seed: int, size: int = _TEXTURE_SIZE) -> list[np.ndarray]:
    """Six distinct (size, size, 3) uint8 RGB face textures, fixed by ``seed``."""
    rng = np.random.default_rng(seed)
    hues = (np.arange(6) * 30 + rng.integers(0, 30)) % 180  # distinct OpenCV hues
    textures = []
    for face in range(6):
        hsv = np.zeros((size, size, 3), np.uint8)
        hsv[..., 0] = hues[face]
        hsv[..., 1] = 200
        hsv[..., 2] = 200
        tex = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        for _ in range(6 + face):
            colour = tuple(int(c) for c in rng.integers(0, 256, 3))
            kind = rng.integers(0, 3)
            a, b = rng.integers(0, size, 2), rng.integers(0, size, 2)
            if kind == 0:
                cv2.rectangle(tex, tuple(map(int, a)), tuple(map(int, b)), colour, -1)
            elif kind == 1:
                cv2.circle(tex, tuple(map(int, a)), int(rng.integers(4, size // 4)), colour, -1)
            else:
                cv2.line(tex, tuple(map(int, a)), tuple(map(int, b)), colour,
                         int(rng.integers(2, 8)))
        cv2.rectangle(tex, (0, 0), (size - 1, size - 1), (20, 20, 20), 3)  # dark edges
        textures.append(tex)
    return textures


def draw_textured_cuboid(
    image: np.ndarray,
    K: np.ndarray,
    pose: np.ndarray,
    cuboid: Cuboid,
    textures: list[np.ndarray],
    light_dir: np.ndarray | None = None,
    ambient: float = 0.45,
) -> np.ndarray:
    """Draw the visible faces of a textured cuboid; returns a new image.

    Args:
        image: (H, W, 3) uint8 background.
        K: (3, 3) intrinsics; pose: (4, 4) object-to-camera (every corner must have z > 0).
        cuboid: the box; textures: six face textures (order of :data:`FACES`).
        light_dir: unit vector towards the light in the camera frame (default: the camera).
        ambient: shading ``ambient + (1 - ambient) * max(0, n . light)``.
    """
    h, w = image.shape[:2]
    corners = cuboid.points()[:8] @ pose[:3, :3].T + pose[:3, 3]
    if np.any(corners[:, 2] <= 1e-6):
        raise ValueError("every cuboid corner must be in front of the camera")
    uv = corners @ np.asarray(K, np.float64).T
    uv = uv[:, :2] / uv[:, 2:3]
    light = np.array([0.0, 0.0, -1.0]) if light_dir is None else np.asarray(light_dir, float)
    # Faces are averaged by their coverage (so shared edges show no seam), then the object is
    # blended over the background through its anti-aliased silhouette (the convex hull).
    colour = np.zeros((h, w, 3), np.float32)
    weight = np.zeros((h, w, 1), np.float32)
    for (idx, axis, sign), tex in zip(FACES, textures, strict=True):
        normal = sign * pose[:3, axis]
        centre = corners[list(idx)].mean(axis=0)
        if normal @ centre >= 0:  # facing away from the camera
            continue
        shade = ambient + (1 - ambient) * max(0.0, float(normal @ light))
        quad = uv[list(idx)]
        x0, y0 = np.maximum(np.floor(quad.min(axis=0)).astype(int) - 1, 0)
        x1, y1 = np.minimum(np.ceil(quad.max(axis=0)).astype(int) + 2, (w, h))
        if x1 <= x0 or y1 <= y0:  # entirely outside the image
            continue
        s = tex.shape[0] - 1
        src = np.float32([[0, 0], [s, 0], [s, s], [0, s]])
        H = cv2.getPerspectiveTransform(src, (quad - (x0, y0)).astype(np.float32))
        size = (int(x1 - x0), int(y1 - y0))
        warped = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR)
        alpha = cv2.warpPerspective(np.ones(tex.shape[:2], np.float32), H, size,
                                    flags=cv2.INTER_LINEAR)[..., None]
        # the warp blends the texture with the black border: ``warped`` is premultiplied
        colour[y0:y1, x0:x1] += warped.astype(np.float32) * shade
        weight[y0:y1, x0:x1] += alpha
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull * _SUBPIXEL).astype(np.int32), 255,
                       lineType=cv2.LINE_AA, shift=_SUBPIXEL_BITS)
    silhouette = mask[..., None].astype(np.float32) / 255.0
    layer = np.divide(colour, weight, out=np.zeros_like(colour), where=weight > 1e-6)
    out = image.astype(np.float32) * (1 - silhouette) + layer * silhouette
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def _background(rng: np.random.Generator, h: int, w: int, n_shapes: int) -> np.ndarray:
    kind = rng.integers(0, 3)
    if kind == 0:  # smooth gradient
        c0, c1 = rng.uniform(0, 255, 3), rng.uniform(0, 255, 3)
        ramp = np.linspace(0, 1, w)[None, :, None] if rng.random() < 0.5 else \
            np.linspace(0, 1, h)[:, None, None]
        img = np.broadcast_to(c0 + (c1 - c0) * ramp, (h, w, 3)).astype(np.uint8)
    elif kind == 1:  # blurred coloured noise
        small = rng.uniform(0, 255, (max(2, h // 16), max(2, w // 16), 3)).astype(np.float32)
        img = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 255)
        img = img.astype(np.uint8)
    else:  # flat colour
        img = np.full((h, w, 3), rng.integers(0, 256, 3), np.uint8)
    img = np.ascontiguousarray(img)
    for _ in range(int(rng.integers(0, n_shapes + 1))):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        p = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        if rng.random() < 0.5:
            q = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.rectangle(img, p, q, colour, -1 if rng.random() < 0.5 else 2)
        else:
            cv2.circle(img, p, int(rng.integers(3, max(4, min(h, w) // 6))), colour, -1)
    return img


class SyntheticCuboidSource:
    """Images of the object's textured cuboid at random poses (see the module docstring).

    Sample ``i`` depends only on ``(seed, i)``. The camera is an ideal pinhole with the
    configured horizontal field of view, principal point at the image centre.
    """

    def __init__(
        self,
        cuboid: Cuboid,
        num_samples: int,
        image_size: tuple[int, int],
        *,
        object_name: str = "cuboid",
        seed: int = 0,
        options: CuboidSourceOptions | None = None,
    ) -> None:
        if num_samples < 0:
            raise ConfigError(f"num_samples must be >= 0, got {num_samples}")
        self.cuboid = cuboid
        self.object_name = object_name
        self.num_samples = int(num_samples)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.seed = int(seed)
        self.options = options or CuboidSourceOptions()
        self.textures = make_face_textures(self.options.texture_seed)
        # distractor appearances: a fixed pool, disjoint from the object's texture seed
        pool_rng = np.random.default_rng([self.options.texture_seed, _DISTRACTOR_POOL])
        self._distractor_textures = [
            make_face_textures(int(pool_rng.integers(1 << 30)) + 1)
            for _ in range(_DISTRACTOR_POOL)
        ]
        h, w = self.image_size
        f = (w / 2) / np.tan(np.radians(self.options.hfov_deg) / 2)
        self.K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], np.float64)
        o = self.options
        self.description = (
            f"{self.num_samples} OpenCV-drawn textured-cuboid images {w}x{h} (seed {seed}, "
            f"texture seed {o.texture_seed}, hfov {o.hfov_deg} deg, distance "
            f"{o.distance_range[0]}-{o.distance_range[1]} diameters, up to "
            f"{o.max_instances} instance(s), random backgrounds, shapes and "
            f"{o.distractor_boxes} distractor boxes)"
        )

    def __len__(self) -> int:
        return self.num_samples

    def _random_pose(self, rng: np.random.Generator, cuboid: Cuboid) -> np.ndarray:
        h, w = self.image_size
        o = self.options
        z = rng.uniform(*o.distance_range) * cuboid.diameter
        u = rng.uniform(o.margin * w, (1 - o.margin) * w)
        v = rng.uniform(o.margin * h, (1 - o.margin) * h)
        centre = np.linalg.solve(self.K, np.array([u, v, 1.0])) * z
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = centre - T[:3, :3] @ np.asarray(cuboid.center)
        return T

    def __getitem__(self, index: int) -> PoseSample:
        if not 0 <= index < self.num_samples:
            raise IndexError(f"sample {index} out of range 0..{self.num_samples - 1}")
        rng = np.random.default_rng([self.seed, int(index)])
        o = self.options
        h, w = self.image_size
        image = _background(rng, h, w, o.distractor_shapes)
        n = 0 if rng.random() < o.empty_probability else int(rng.integers(1, o.max_instances + 1))
        draws: list[tuple[float, np.ndarray, Cuboid, list[np.ndarray]]] = []
        poses = []
        for _ in range(n):
            T = self._random_pose(rng, self.cuboid)
            poses.append(T)
            draws.append((float(T[2, 3]), T, self.cuboid, self.textures))
        for _ in range(int(rng.integers(0, o.distractor_boxes + 1))):
            dims = tuple(rng.uniform(0.3, 1.5, 3) * np.asarray(self.cuboid.dimensions))
            box = Cuboid(dims)
            T = self._random_pose(rng, box)
            tex = self._distractor_textures[int(rng.integers(_DISTRACTOR_POOL))]
            draws.append((float(T[2, 3]), T, box, tex))
        light = rng.normal(size=3)
        light[2] = -abs(light[2])  # from the camera's side
        light /= np.linalg.norm(light)
        for _, T, box, tex in sorted(draws, key=lambda d: -d[0]):  # far to near
            image = draw_textured_cuboid(image, self.K, T, box, tex, light, o.ambient)
        poses_arr = np.array(poses, np.float64).reshape(-1, 4, 4)
        return PoseSample(
            image=image,
            K=self.K.copy(),
            poses=poses_arr,
            keypoints=project_keypoints(self.cuboid, poses_arr, self.K),
        )


@register_source("cuboid")
def _cuboid_factory(spec: SourceSpec) -> SyntheticCuboidSource:
    return SyntheticCuboidSource(
        spec.cuboid, spec.num_samples, spec.image_size, object_name=spec.object_name,
        seed=spec.seed, options=CuboidSourceOptions.from_dict(spec.options, spec.options_key),
    )
