"""The pinhole camera with optional OpenCV distortion, over kornia's calibration functions."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
import yaml
from kornia.geometry.calibration import distort_points, undistort_points
from torch import Tensor

from evtrack.errors import ConfigError

__all__ = ["PinholeCamera"]

_FIELDS = ("fx", "fy", "cx", "cy", "width", "height")
_DIST_LENGTHS = (4, 5, 8, 12, 14)


class PinholeCamera:
    """A pinhole camera in the OpenCV convention (x right, y down, z forward).

    Args:
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (pixel centres at integer coordinates).
        width, height: image size in pixels.
        dist: OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, ...]]])``
            with 4, 5, 8, 12 or 14 entries, or ``None`` for an ideal pinhole.

    Example:
        >>> cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
        >>> cam.project(torch.tensor([[0.0, 0.0, 1.0]])).tolist()
        [[320.0, 240.0]]
    """

    def __init__(
        self,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        dist: Sequence[float] | Tensor | None = None,
    ) -> None:
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (fx, fy, cx, cy))
        self.width, self.height = int(width), int(height)
        if not (self.fx > 0 and self.fy > 0):
            raise ConfigError(f"camera focal lengths must be positive, got fx={fx}, fy={fy}")
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"camera size must be positive, got {width}x{height}")
        if dist is not None:
            d = torch.as_tensor(dist, dtype=torch.float64).flatten()
            if d.numel() not in _DIST_LENGTHS:
                raise ConfigError(
                    f"camera dist must have one of {_DIST_LENGTHS} coefficients, got {d.numel()}"
                )
            dist = None if bool((d == 0).all()) else d
        self.dist: Tensor | None = dist

    # ------------------------------------------------------------------ properties
    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self.width, self.height

    def K(self, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu") -> Tensor:
        """The 3x3 intrinsic matrix."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=dtype,
            device=device,
        )

    def _dist_like(self, x: Tensor) -> Tensor:
        assert self.dist is not None
        return self.dist.to(dtype=x.dtype, device=x.device)

    # ------------------------------------------------------------------ geometry
    def project(self, points: Tensor) -> Tensor:
        """Project camera-frame points to pixels (distortion applied if set).

        Args:
            points: (*, 3) metres, z > 0 in front of the camera.

        Returns:
            (*, 2) pixel coordinates ``(u, v)``.
        """
        z = points[..., 2:3]
        xn = points[..., :2] / z
        if self.dist is None:
            u = self.fx * xn[..., 0] + self.cx
            v = self.fy * xn[..., 1] + self.cy
            return torch.stack([u, v], dim=-1)
        uv_ideal = self._ideal_pixels(xn)
        return self.distort_points(uv_ideal)

    def _ideal_pixels(self, xn: Tensor) -> Tensor:
        return torch.stack([self.fx * xn[..., 0] + self.cx, self.fy * xn[..., 1] + self.cy], -1)

    def distort_points(self, uv: Tensor) -> Tensor:
        """Ideal (undistorted) pixels (*, 2) -> distorted pixels (*, 2)."""
        if self.dist is None:
            return uv.clone()
        flat = uv.reshape(1, -1, 2)
        K = self.K(uv.dtype, uv.device)
        return distort_points(flat, K, self._dist_like(uv)).reshape(uv.shape)

    def undistort_points(self, uv: Tensor, num_iters: int = 20) -> Tensor:
        """Distorted pixels (*, 2) -> ideal pinhole pixels (*, 2) (iterative inverse)."""
        if self.dist is None:
            return uv.clone()
        flat = uv.reshape(1, -1, 2)
        K = self.K(uv.dtype, uv.device)
        out = undistort_points(flat, K, self._dist_like(uv), num_iters=num_iters)
        return out.reshape(uv.shape)

    def unproject(self, uv: Tensor, depth: Tensor) -> Tensor:
        """Back-project pixels with their depth (z, metres) to camera-frame points.

        Args:
            uv: (*, 2) pixel coordinates (distorted if the camera has distortion).
            depth: (*) z-depth in metres.

        Returns:
            (*, 3) points with ``P[..., 2] == depth``.
        """
        uv = self.undistort_points(uv)
        x = (uv[..., 0] - self.cx) / self.fx * depth
        y = (uv[..., 1] - self.cy) / self.fy * depth
        return torch.stack([x, y, depth.to(x.dtype)], dim=-1)

    def in_image(self, uv: Tensor) -> Tensor:
        """(*, 2) -> (*) bool: inside ``[-0.5, width-0.5) x [-0.5, height-0.5)``."""
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u < self.width - 0.5) & (v >= -0.5) & (v < self.height - 0.5)

    def scaled(self, factor: float) -> PinholeCamera:
        """The same camera at ``factor`` times the resolution (pixel-centre convention kept)."""
        return PinholeCamera(
            self.fx * factor, self.fy * factor,
            (self.cx + 0.5) * factor - 0.5, (self.cy + 0.5) * factor - 0.5,
            round(self.width * factor), round(self.height * factor),
            None if self.dist is None else self.dist.clone(),
        )

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {k: getattr(self, k) for k in _FIELDS}
        d["dist"] = None if self.dist is None else [float(v) for v in self.dist]
        return d

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "camera") -> PinholeCamera:
        """Build from a mapping with ``fx, fy, cx, cy, width, height`` and optional ``dist``.

        Raises:
            ConfigError: naming ``source`` and the missing or invalid field.
        """
        if not isinstance(data, Mapping):
            raise ConfigError(
                f"{source}: expected a mapping of camera fields, got {type(data).__name__}"
            )
        missing = [k for k in _FIELDS if k not in data]
        if missing:
            raise ConfigError(f"{source}: missing camera field(s) {missing}")
        unknown = sorted(set(data) - set(_FIELDS) - {"dist"})
        if unknown:
            raise ConfigError(f"{source}: unknown camera field(s) {unknown}")
        for k in _FIELDS:
            v = data[k]
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"{source}: camera field {k!r} must be a number, got {v!r}")
            if k in ("width", "height") and v != int(v):
                raise ConfigError(f"{source}: camera field {k!r} must be a whole number of "
                                  f"pixels, got {v!r}")
        try:
            return cls(**{k: data[k] for k in _FIELDS}, dist=data.get("dist"))
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: invalid camera field: {exc}") from exc

    def to_yaml(self, path: str | Path) -> None:
        from evtrack.utils import atomic_write_text

        atomic_write_text(path, yaml.safe_dump(self.to_dict(), sort_keys=False))

    @classmethod
    def from_yaml(cls, path: str | Path) -> PinholeCamera:
        with open(path) as fh:
            data = yaml.safe_load(fh)
        return cls.from_dict(data, source=str(path))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PinholeCamera):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None

    def __repr__(self) -> str:
        dist = "" if self.dist is None else f", dist={[round(float(v), 6) for v in self.dist]}"
        return (
            f"PinholeCamera(fx={self.fx}, fy={self.fy}, cx={self.cx}, cy={self.cy}, "
            f"width={self.width}, height={self.height}{dist})"
        )
