"""The object's 3-D cuboid: the 8 corners + centroid whose projections the network predicts.

Corner order (object frame, ``c`` = cuboid centre, ``d`` = full dimensions along x, y, z)::

    index k = 4*bx + 2*by + bz  with  corner_k = c + (d/2) * (2*bx-1, 2*by-1, 2*bz-1)

i.e. ``0: (-,-,-)``, ``1: (-,-,+)``, ``2: (-,+,-)``, ``3: (-,+,+)``, ``4: (+,-,-)``,
``5: (+,-,+)``, ``6: (+,+,-)``, ``7: (+,+,+)``; keypoint 8 is the centre ``c``. Belief map ``k``
and affinity channels ``2k, 2k+1`` of the network follow the same order.

The cuboid is the axis-aligned bounding box of the mesh in the object's own frame, so the pose
that PnP recovers is the pose of the *mesh* frame (the centre need not be the mesh origin).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evtrack.errors import ConfigError

__all__ = ["Cuboid", "NUM_KEYPOINTS", "CENTROID_INDEX"]

NUM_KEYPOINTS = 9
CENTROID_INDEX = 8

_SIGNS = np.array(
    [[2 * ((k >> 2) & 1) - 1, 2 * ((k >> 1) & 1) - 1, 2 * (k & 1) - 1] for k in range(8)],
    dtype=np.float64,
)


@dataclass(frozen=True)
class Cuboid:
    """An object's bounding cuboid in its own frame.

    Attributes:
        dimensions: full extent along the object's x, y, z axes, metres (all > 0).
        center: the cuboid centre in the object frame, metres.
    """

    dimensions: tuple[float, float, float]
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        dims = tuple(float(v) for v in self.dimensions)
        ctr = tuple(float(v) for v in self.center)
        if len(dims) != 3 or len(ctr) != 3:
            raise ConfigError(
                f"cuboid needs 3 dimensions and a 3-D center, got {self.dimensions}, {self.center}"
            )
        if not all(np.isfinite(dims)) or min(dims) <= 0:
            raise ConfigError(f"cuboid dimensions must be positive metres, got {dims}")
        if not all(np.isfinite(ctr)):
            raise ConfigError(f"cuboid center must be finite, got {ctr}")
        object.__setattr__(self, "dimensions", dims)
        object.__setattr__(self, "center", ctr)

    @classmethod
    def from_mesh(cls, mesh: Any) -> Cuboid:
        """The axis-aligned bounding box of a mesh (a path trimesh can load, or a trimesh object).

        A BOP model file (``obj_000005.ply`` beside a ``models_info.json``) is in millimetres
        and gives its box in metres.

        Raises:
            ConfigError: when the file cannot be loaded or holds no geometry.
        """
        import trimesh

        source = mesh
        scale = 1.0
        if isinstance(mesh, (str, Path)):
            from evtrack.datasets.bop import MM, is_bop_model_file

            path = Path(mesh)
            if not path.is_file():
                raise ConfigError(f"{path}: mesh file not found")
            try:
                mesh = trimesh.load(path, force="scene")
            except Exception as exc:  # trimesh raises many types for bad files
                raise ConfigError(f"{path}: cannot load mesh: {exc}") from exc
            scale = MM if is_bop_model_file(path) else 1.0
        bounds = getattr(mesh, "bounds", None)
        if bounds is None or not np.all(np.isfinite(bounds)):
            raise ConfigError(f"{source}: mesh has no finite bounds (empty geometry?)")
        lo, hi = np.asarray(bounds, dtype=np.float64) * scale
        return cls(tuple(hi - lo), tuple((hi + lo) / 2))

    @classmethod
    def from_dict(cls, data: Any, source: str = "cuboid") -> Cuboid:
        """From ``{"dimensions": [dx, dy, dz], "center": [cx, cy, cz]}`` (center optional)."""
        if not isinstance(data, dict) or "dimensions" not in data:
            raise ConfigError(f"{source}: expected a mapping with 'dimensions' (and 'center')")
        unknown = sorted(set(data) - {"dimensions", "center"})
        if unknown:
            raise ConfigError(f"{source}: unknown cuboid field(s) {unknown}")
        return cls(tuple(data["dimensions"]), tuple(data.get("center", (0.0, 0.0, 0.0))))

    def to_dict(self) -> dict[str, list[float]]:
        return {"dimensions": list(self.dimensions), "center": list(self.center)}

    def points(self) -> np.ndarray:
        """(9, 3) float64: the 8 corners in the documented order, then the centre (metres)."""
        c = np.asarray(self.center)
        half = np.asarray(self.dimensions) / 2
        return np.concatenate([c + _SIGNS * half, c[None]], axis=0)

    @property
    def diameter(self) -> float:
        """The cuboid's space diagonal, metres (an upper bound of the object's diameter)."""
        return float(np.linalg.norm(self.dimensions))

    def project(
        self, pose: np.ndarray, K: np.ndarray, dist: Sequence[float] | None = None
    ) -> np.ndarray:
        """Project the 9 keypoints with an object-to-camera pose.

        Args:
            pose: (4, 4) object-to-camera.
            K: (3, 3) intrinsics.
            dist: OpenCV distortion coefficients or ``None``.

        Returns:
            (9, 2) pixels.
        """
        import cv2

        pose = np.asarray(pose, dtype=np.float64)
        rvec, _ = cv2.Rodrigues(pose[:3, :3])
        uv, _ = cv2.projectPoints(
            self.points(), rvec, pose[:3, 3], np.asarray(K, dtype=np.float64),
            None if dist is None else np.asarray(dist, dtype=np.float64),
        )
        return uv.reshape(NUM_KEYPOINTS, 2)
