"""Training samples and the pluggable sources that produce them.

A *source* is any object with ``len(source)`` and ``source[i] -> PoseSample`` that returns the
same sample for the same index (seeded by the index), plus three attributes: ``object_name``,
``cuboid`` and ``description`` (one line for the model card's "training data"). Sources are
registered by kind with :func:`register_source`, so a YAML config picks one by name::

    data:
      source: cuboid          # a registered kind: cuboid (OpenCV-drawn box), shards, sim, bop
      options: {...}          # keyword options of that kind
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np

from evtrack.errors import ConfigError
from evtrack.models.cuboid import NUM_KEYPOINTS, Cuboid

__all__ = [
    "PoseSample",
    "SampleSource",
    "SourceSpec",
    "register_source",
    "build_source",
    "list_sources",
    "project_keypoints",
]


@dataclass(frozen=True)
class PoseSample:
    """One training image with its object instances.

    Attributes:
        image: (H, W, 3) uint8 RGB.
        K: (3, 3) float64 intrinsics of this (possibly augmented) image.
        poses: (N, 4, 4) float64 object-to-camera poses of the N instances (N may be 0).
        keypoints: (N, 9, 2) float32 projected cuboid keypoints (8 corners, centroid), pixels,
            NaN where unknown.
    """

    image: np.ndarray
    K: np.ndarray
    poses: np.ndarray
    keypoints: np.ndarray

    @property
    def num_instances(self) -> int:
        return int(self.poses.shape[0])

    def replace(self, **changes: Any) -> PoseSample:
        """A copy with some fields replaced (the sample itself is never modified)."""
        return replace(self, **changes)

    def check(self, where: str = "sample") -> PoseSample:
        """Raise ``ValueError`` naming ``where`` and the problem if any field is malformed."""
        im = self.image
        if not (isinstance(im, np.ndarray) and im.dtype == np.uint8 and im.ndim == 3
                and im.shape[2] == 3):
            raise ValueError(f"{where}: image must be uint8 (H, W, 3), got "
                             f"{getattr(im, 'dtype', type(im))} {getattr(im, 'shape', '')}")
        if np.asarray(self.K).shape != (3, 3):
            raise ValueError(f"{where}: K must be (3, 3), got {np.asarray(self.K).shape}")
        n = self.num_instances
        if self.poses.shape != (n, 4, 4):
            raise ValueError(f"{where}: poses must be (N, 4, 4), got {self.poses.shape}")
        if self.keypoints.shape != (n, NUM_KEYPOINTS, 2):
            raise ValueError(f"{where}: keypoints must be ({n}, 9, 2), got "
                             f"{self.keypoints.shape}")
        return self


def project_keypoints(cuboid: Cuboid, poses: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses -> (N, 9, 2) float32 pinhole projections of the cuboid keypoints."""
    pts = cuboid.points()
    out = np.empty((len(poses), NUM_KEYPOINTS, 2), np.float32)
    for i, T in enumerate(poses):
        P = pts @ T[:3, :3].T + T[:3, 3]
        uvw = P @ np.asarray(K, np.float64).T
        out[i] = uvw[:, :2] / uvw[:, 2:3]
    return out


@runtime_checkable
class SampleSource(Protocol):
    """What the data module needs from a source of samples."""

    object_name: str
    cuboid: Cuboid
    description: str

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> PoseSample: ...


@dataclass(frozen=True)
class SourceSpec:
    """Everything a source factory receives.

    Attributes:
        options: the kind-specific options from the config.
        object_name: the object to show.
        cuboid: its cuboid.
        mesh: its mesh file (or ``None`` when only the cuboid is known).
        num_samples: how many samples the source must provide.
        image_size: ``(height, width)`` of the images.
        seed: base seed (the same seed gives the same samples).
        options_key: where ``options`` are in the config (``data.options`` or
            ``data.val_options``); errors about them start with it.
    """

    options: dict[str, Any]
    object_name: str
    cuboid: Cuboid
    mesh: str | None
    num_samples: int
    image_size: tuple[int, int]
    seed: int
    options_key: str = "data.options"


_FACTORIES: dict[str, Callable[[SourceSpec], SampleSource]] = {}


def register_source(kind: str) -> Callable:
    """Decorator registering ``factory(spec: SourceSpec) -> SampleSource`` under ``kind``."""

    def deco(factory: Callable[[SourceSpec], SampleSource]) -> Callable:
        if kind in _FACTORIES:
            raise ValueError(f"sample source kind {kind!r} is already registered")
        _FACTORIES[kind] = factory
        return factory

    return deco


def list_sources() -> list[str]:
    """Registered source kinds."""
    _import_builtin_sources()
    return sorted(_FACTORIES)


def build_source(kind: str, spec: SourceSpec) -> SampleSource:
    """Build the source ``kind``.

    Raises:
        ConfigError: unknown kind, or options the factory rejects.
    """
    _import_builtin_sources()
    if kind not in _FACTORIES:
        raise ConfigError(f"data.source: unknown kind {kind!r}; known: {sorted(_FACTORIES)}")
    source = _FACTORIES[kind](spec)
    if len(source) != spec.num_samples:
        raise ConfigError(f"data.source {kind!r} provides {len(source)} samples, "
                          f"{spec.num_samples} were asked for")
    return source


def _import_builtin_sources() -> None:
    # the built-in kinds register themselves on import
    from evtrack.train import bop_source, cuboid_source, shards, sim_source  # noqa: F401
