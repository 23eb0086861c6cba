"""The event model: exact crossings and timestamps, refractory rule against a per-pixel loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.sim.config import EventConfig
from evtrack.sim.esim import EventSimulator, log_intensity, simulate_reference

EXACT = EventConfig(threshold_mismatch=0.0, refractory_us=0.0)


def _run(sim: EventSimulator, frames: np.ndarray, times: np.ndarray):
    sim.reset(torch.from_numpy(frames[0]), int(times[0]))
    chunks = [sim.step(torch.from_numpy(f), int(t)) for f, t in zip(frames[1:], times[1:],
                                                                     strict=True)]
    out = {k: np.concatenate([getattr(c, k).cpu().numpy() for c in chunks]).astype(np.int64)
           for k in ("x", "y", "t", "p")}
    return out, chunks


def test_static_scene_emits_nothing() -> None:
    rng = np.random.default_rng(0)
    frame = rng.normal(0.0, 1.0, (12, 16)).astype(np.float32)
    frames = np.stack([frame] * 6)
    sim = EventSimulator(16, 12, EventConfig(threshold_mismatch=0.1), seed=3)
    out, _ = _run(sim, frames, np.arange(6) * 2000)
    assert len(out["t"]) == 0


@pytest.mark.parametrize("k", [1, 2, 5])
def test_k_thresholds_give_k_events_at_interpolated_times(k: int) -> None:
    c = 0.2
    rise = (k + 0.5) * c  # between k and k+1 thresholds
    f0 = np.zeros((3, 4), np.float32)
    f1 = f0.copy()
    f1[1, 2] = rise
    sim = EventSimulator(4, 3, EXACT)
    sim.reset(torch.from_numpy(f0), 10_000)
    ev = sim.step(torch.from_numpy(f1), 12_000)
    assert len(ev) == k
    assert (ev.p == 1).all() and (ev.x == 2).all() and (ev.y == 1).all()
    expected = [10_000 + round(i * c / rise * 2000) for i in range(1, k + 1)]
    assert ev.t.tolist() == expected
    assert ev.t.dtype == torch.int64


def test_off_events_and_remainder_carried_to_next_interval() -> None:
    c = 0.2
    f = np.zeros((3, 1, 1), np.float32)
    f[1] = -0.3  # 1 OFF at 2/3 of the interval, remainder -0.1
    f[2] = -0.45  # reaches -0.4: a second OFF at (0.1/0.15) of the next interval
    sim = EventSimulator(1, 1, EXACT)
    out, _ = _run(sim, f, np.array([0, 3000, 6000]))
    assert out["p"].tolist() == [-1, -1]
    assert out["t"].tolist() == [round(c / 0.3 * 3000), 3000 + round(0.1 / 0.15 * 3000)]


def test_matches_per_pixel_reference_loop() -> None:
    """Random log-intensity walks, mismatched thresholds, refractory: batched == plain loop."""
    rng = np.random.default_rng(1)
    h, w, k = 6, 7, 12
    frames = np.cumsum(rng.normal(0.0, 0.6, (k, h, w)), axis=0).astype(np.float32)
    times = np.cumsum(np.concatenate([[0], rng.integers(500, 3000, k - 1)]))
    counts = []
    for refractory in (0.0, 150.0, 900.0):
        cfg = EventConfig(threshold_mismatch=0.2, refractory_us=refractory)
        sim = EventSimulator(w, h, cfg, seed=5)
        c_on = sim.c_on.reshape(h, w).numpy()
        c_off = sim.c_off.reshape(h, w).numpy()
        out, _ = _run(sim, frames, times)
        ref = simulate_reference(frames.astype(np.float64), times, c_on, c_off, refractory)
        assert len(ref["t"]) > 50
        assert len(out["t"]) == len(ref["t"]), refractory
        for key in ("x", "y", "p"):
            np.testing.assert_array_equal(out[key], ref[key], err_msg=f"{key} R={refractory}")
        assert np.abs(out["t"] - ref["t"]).max() <= 1
        counts.append(len(out["t"]))
    assert counts[0] > counts[1] > counts[2]  # the refractory period drops events


def test_refractory_spacing_and_sorted_output() -> None:
    rng = np.random.default_rng(2)
    frames = np.cumsum(rng.normal(0.0, 0.8, (10, 8, 8)), axis=0).astype(np.float32)
    times = np.arange(10) * 2000
    sim = EventSimulator(8, 8, EventConfig(refractory_us=400.0), seed=1)
    out, chunks = _run(sim, frames, times)
    assert all(c.validate().ok for c in chunks)
    assert (np.diff(out["t"]) >= 0).all()
    pix = out["y"] * 8 + out["x"]
    for p in np.unique(pix):
        t = out["t"][pix == p]
        assert (np.diff(t) >= 400 - 1).all()  # rounding to µs may cost 1 µs


def test_ties_are_ordered_by_pixel_index() -> None:
    f0 = np.zeros((2, 3), np.float32)
    f1 = np.full((2, 3), 0.25, np.float32)  # every pixel crosses once at the same time
    sim = EventSimulator(3, 2, EXACT)
    sim.reset(torch.from_numpy(f0), 0)
    ev = sim.step(torch.from_numpy(f1), 1000)
    assert (ev.y.long() * 3 + ev.x.long()).tolist() == list(range(6))


def test_seeded_mismatch_and_noise() -> None:
    cfg = EventConfig(threshold_mismatch=0.1, shot_noise_hz=50.0, leak_noise_hz=5.0)
    a = EventSimulator(32, 24, cfg, seed=7)
    b = EventSimulator(32, 24, cfg, seed=7)
    c = EventSimulator(32, 24, cfg, seed=8)
    assert torch.equal(a.c_on, b.c_on) and not torch.equal(a.c_on, c.c_on)
    frames = np.zeros((5, 24, 32), np.float32)
    ea, _ = _run(a, frames, np.arange(5) * 20_000)
    eb, _ = _run(b, frames, np.arange(5) * 20_000)
    ec, _ = _run(c, frames, np.arange(5) * 20_000)
    for key in ea:
        np.testing.assert_array_equal(ea[key], eb[key])
    assert len(ea["t"]) != len(ec["t"]) or not np.array_equal(ea["t"], ec["t"])


def test_noise_rates() -> None:
    """Shot noise is Poisson at shot_hz per pixel; leak gives ON events at about leak_hz."""
    h, w, seconds = 20, 30, 2.0
    frames = np.zeros((21, h, w), np.float32)
    times = np.linspace(0, seconds * 1e6, 21).astype(np.int64)
    shot = EventSimulator(w, h, EventConfig(shot_noise_hz=5.0), seed=0)
    out, _ = _run(shot, frames, times)
    expected = 5.0 * h * w * seconds
    assert abs(len(out["t"]) - expected) < 5 * np.sqrt(expected)
    assert abs((out["p"] > 0).mean() - 0.5) < 0.05
    leak = EventSimulator(w, h, EventConfig(leak_noise_hz=2.0, leak_mismatch=0.0), seed=0)
    out, _ = _run(leak, frames, times)
    assert (out["p"] == 1).all()
    rate = len(out["t"]) / (h * w * seconds)
    assert 1.5 < rate < 2.5  # the random initial phase adds up to one event per pixel


def test_log_intensity() -> None:
    rgb = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    out = log_intensity(rgb, 0.01)
    assert torch.allclose(out, torch.log(torch.tensor([1.01, 0.01, 0.2126 + 0.01])))


def test_bad_inputs() -> None:
    sim = EventSimulator(4, 3, EXACT)
    with pytest.raises(RuntimeError, match="before reset"):
        sim.step(torch.zeros(3, 4), 10)
    sim.reset(torch.zeros(3, 4), 100)
    with pytest.raises(ValueError, match="not after"):
        sim.step(torch.zeros(3, 4), 100)
    with pytest.raises(ValueError, match="frame must be"):
        sim.step(torch.zeros(4, 3), 200)


def test_device_matches_cpu(device: torch.device) -> None:
    rng = np.random.default_rng(4)
    frames = np.cumsum(rng.normal(0.0, 0.3, (6, 10, 12)), axis=0).astype(np.float32)
    times = np.arange(6) * 1500
    cfg = EventConfig(threshold_mismatch=0.0, refractory_us=200.0)
    cpu, _ = _run(EventSimulator(12, 10, cfg, device="cpu"), frames, times)
    dev, chunks = _run(EventSimulator(12, 10, cfg, device=device), frames, times)
    assert chunks[0].device.type == device.type
    for key in cpu:
        np.testing.assert_array_equal(cpu[key], dev[key])
