"""The tracker's sensor-noise stage (``TrackerConfig.denoise``): off by default, on it removes
injected background activity and a hot pixel as the events are pushed, counts them, and the
track goes on."""

from __future__ import annotations

import numpy as np
from tracker_helpers import make_tracker

from evtrack import Sequence
from evtrack.events import Events
from evtrack.tracking.trajectory import STATUS_TRACKING

HOT = (40, 50)


def _noisy(seq: Sequence, seed: int = 0, noise_hz: float = 2.0, hot_hz: float = 2000.0
           ) -> tuple[Sequence, int, int]:
    """A copy of ``seq`` whose events have background activity (``noise_hz`` per pixel) and a
    hot pixel (``hot_hz``) added; with the numbers of each."""
    ev = seq.events
    w, h = ev.sensor_size
    rng = np.random.default_rng(seed)
    t0, t1 = int(ev.t[0]), int(ev.t[-1])
    n_noise = rng.poisson(noise_hz * (t1 - t0) * 1e-6 * w * h)
    n_hot = int(hot_hz * (t1 - t0) * 1e-6)
    t = np.concatenate([ev.t.numpy(), rng.integers(t0, t1, n_noise), rng.integers(t0, t1, n_hot)])
    x = np.concatenate([ev.x.numpy(), rng.integers(0, w, n_noise), np.full(n_hot, HOT[0])])
    y = np.concatenate([ev.y.numpy(), rng.integers(0, h, n_noise), np.full(n_hot, HOT[1])])
    p = np.concatenate([ev.p.numpy(), rng.choice([-1, 1], n_noise), np.ones(n_hot, int)])
    order = np.argsort(t, kind="stable")
    noisy = Events(x[order].astype(np.int16), y[order].astype(np.int16), t[order],
                   p[order].astype(np.int8), (w, h))
    copy = Sequence.load(seq.root)
    copy.iter_events = lambda window_us=None, count=None: noisy.windows(duration_us=window_us,
                                                                        count=count)
    return copy, n_noise, n_hot


def test_off_by_default_and_for_methods_without_events(fast_sequence) -> None:
    tracker, _ = make_tracker(fast_sequence)
    assert tracker.gate.denoiser is None
    on = {"denoise": {"method": "background_activity", "hot_pixels": True}}
    assert make_tracker(fast_sequence, method="pose", **on)[0].gate.denoiser is None
    assert make_tracker(fast_sequence, method="full", **on)[0].gate.denoiser is not None


def test_tracker_removes_noise_and_a_hot_pixel_and_counts_them(fast_sequence) -> None:
    seq, n_noise, n_hot = _noisy(fast_sequence)
    # a 5 ms window: this sparse simulated stream loses 17 % of its events to a 2 ms one
    tracker, _ = make_tracker(seq, method="full", denoise={
        "method": "background_activity", "window_us": 5000, "hot_pixels": True})
    traj = tracker.track(seq)
    st = tracker.stats
    assert st.events == len(fast_sequence.events) + n_noise + n_hot
    assert st.hot_pixels == 1
    assert 0.7 * n_hot < st.events_on_hot_pixels <= n_hot + 20
    assert 0.6 * n_noise < st.events_denoised < n_noise + 0.1 * len(fast_sequence.events)
    assert tracker.gate.denoiser.counts.events_out == (
        st.events - st.events_denoised - st.events_on_hot_pixels)
    assert float((traj.status == STATUS_TRACKING).float().mean()) > 0.8
    assert traj.meta["stats"]["events_denoised"] == st.events_denoised


def test_track_command_prints_what_was_removed(fast_sequence, tmp_path, capsys) -> None:
    from evtrack.cli import main

    config = tmp_path / "denoise.yaml"
    config.write_text("denoise:\n  method: background_activity\n  hot_pixels: true\n")
    out = tmp_path / "traj.csv"
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--oracle", "--quiet",
                 "--config", str(config)]) == 0
    text = capsys.readouterr().out
    assert "removed as noise" in text and "hot pixels" in text
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--method", "pose",
                 "--oracle", "--quiet"]) == 0
    assert "removed as noise" not in capsys.readouterr().out
