"""Fixtures for the io tests: synthetic event streams (seeded) and the real sample files."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from evtrack.events import Events


def make_events(
    n: int,
    *,
    seed: int = 0,
    sensor_size: tuple[int, int] = (640, 480),
    t0: int = 1_000_000,
    mean_dt: int = 7,
    coord_dtype: type = np.int16,
) -> Events:
    """``n`` random valid events (sorted, with repeated timestamps), reproducible by ``seed``."""
    rng = np.random.default_rng(seed)
    w, h = sensor_size
    t = t0 + np.cumsum(rng.integers(0, 2 * mean_dt + 1, n))
    return Events(
        rng.integers(0, w, n).astype(coord_dtype),
        rng.integers(0, h, n).astype(coord_dtype),
        t.astype(np.int64),
        rng.choice(np.array([-1, 1], dtype=np.int8), n),
        sensor_size,
    )


@pytest.fixture
def events_factory() -> Callable[..., Events]:
    return make_events


@pytest.fixture(scope="session")
def evt3_file(formats_dir: Path) -> Path:
    return formats_dir / "expelliarmus_prophesee_raw" / "evt3_sample.raw"


@pytest.fixture(scope="session")
def evt3_reference(formats_dir: Path) -> np.ndarray:
    return np.load(formats_dir / "expelliarmus_prophesee_raw" / "evt3_sample.npy")


@pytest.fixture(scope="session")
def evt2_file(formats_dir: Path) -> Path:
    return formats_dir / "expelliarmus_prophesee_raw" / "evt2_sample.raw"


@pytest.fixture(scope="session")
def aedat4_file(formats_dir: Path) -> Path:
    return formats_dir / "tonic_dvxplorer_aedat4" / "sample.aedat4"
