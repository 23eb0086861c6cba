"""The denoiser on the real recordings of ../shared: the Prophesee EVT2 sample's hot pixel,
windows equal to one call, and an ECD DAVIS240C cut (no hot pixel, some background activity)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evtrack.denoise import DenoiseConfig, EventDenoiser
from evtrack.events import concatenate
from evtrack.io import read_events

pytestmark = pytest.mark.shared

CONFIG = DenoiseConfig(method="background_activity", window_us=2000, hot_pixels=True,
                       hot_window_us=10_000)


@pytest.fixture(scope="module")
def evt2(formats_dir: Path):
    path = formats_dir / "expelliarmus_prophesee_raw" / "evt2_sample.raw"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    return read_events(path)


def test_evt2_hot_pixel_found_and_windows_equal_one_call(evt2) -> None:
    whole = EventDenoiser(CONFIG, sensor_size=evt2.sensor_size)
    out = whole(evt2)
    c = whole.counts
    # (565, 296) fires ~66 kHz all through the 50 ms sample, with no event around it
    assert whole.hot_mask[296, 565] and 1 <= c.hot_pixels_found <= 5
    assert c.removed_hot > 2000 and 0 < c.removed_noise < 0.05 * len(evt2)
    assert len(out) == c.events_out and bool((out.t[1:] >= out.t[:-1]).all())
    streamed = EventDenoiser(CONFIG, sensor_size=evt2.sensor_size)
    cuts = np.linspace(0, len(evt2), 8).astype(int)
    parts = [streamed(evt2[int(a):int(b)]) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    assert concatenate(parts) == out and streamed.counts == c


def test_ecd_davis_cut_has_no_hot_pixel(shared_dir: Path) -> None:
    path = shared_dir / "data" / "real" / "ecd_shapes_rotation_sample" / "events.txt"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    ev = read_events(path, sensor_size=(240, 180))
    denoiser = EventDenoiser(CONFIG, sensor_size=(240, 180))
    out = denoiser(ev)
    assert denoiser.counts.hot_pixels_found == 0
    assert 0.05 * len(ev) < len(ev) - len(out) < 0.5 * len(ev)
