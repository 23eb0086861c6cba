"""Shared fixtures: small simulated sequences (evtrack.sim) and cached tracker runs.

The fast sequence is 128x96 px, 0.6 s of the ``faster`` preset with a procedural box (median
pixel speed 150 px/s, i.e. 770 px/s at 640x480); contrast threshold 0.5 keeps it to ~32k events
so that a full tracker run takes about 4 s of CPU.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from evtrack import Sequence
from evtrack.pose_sources import OraclePoseSource
from evtrack.sim.config import EventConfig, GroundTruthConfig, SimConfig, TrajectoryConfig
from evtrack.sim.engine import sequence_trajectory, simulate
from evtrack.sim.objects import procedural_object
from evtrack.sim.trajectory import static_trajectory
from evtrack.tracker import Tracker
from evtrack.tracking_config import TrackerConfig

# Tracker settings of the accuracy tests: RoIs sized for 128x96 images, poses at 10 Hz
# arriving 100 ms late (the 0.6 s sequence then holds 6 poses), GE contrast = the threshold.
TEST_TRACKER = {"flow": {"roi_size": 16}, "pose_rate_hz": 10.0, "pose_latency_ms": 100.0,
                "ge": {"contrast": 0.5}}
ORACLE_NOISE = {"std_translation": 0.01, "std_rotation": 0.03}


def sim_config(duration: float, seed: int) -> SimConfig:
    cfg = SimConfig(duration=duration, seed=seed, trajectory=TrajectoryConfig(preset="faster"),
                    events=EventConfig(threshold_on=0.5, threshold_off=0.5),
                    ground_truth=GroundTruthConfig(event_flow=False))
    return dataclasses.replace(cfg, camera=cfg.camera.resized(128, 96))


@pytest.fixture(scope="session", autouse=True)
def one_thread():
    """One torch thread: the per-step tensors are tiny, and on 2 busy cores two threads make
    them several times slower (measured 7x on this suite)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def box():
    return procedural_object("box", 0)


@pytest.fixture(scope="session")
def fast_sequence(tmp_path_factory, box) -> Sequence:
    out = tmp_path_factory.mktemp("tracker") / "fast"
    simulate(box, sim_config(0.6, 3), out)
    return Sequence.load(out)


@pytest.fixture(scope="session")
def static_sequence(tmp_path_factory, box) -> Sequence:
    """The object at rest for 0.4 s (no events: the scene is static, the sensor noiseless)."""
    cfg = sim_config(0.4, 3)
    pose = sequence_trajectory(cfg, box).pose(0.3)
    out = tmp_path_factory.mktemp("tracker") / "static"
    simulate(box, cfg, out, trajectory=static_trajectory(pose, 0.5))
    return Sequence.load(out)


def make_tracker(seq: Sequence, seed: int = 0, oracle: dict | None = None,
                 **config) -> tuple[Tracker, OraclePoseSource]:
    """A tracker for ``seq`` with a noisy oracle pose source and the test settings."""
    data = {**TEST_TRACKER, **config}
    source = OraclePoseSource.from_sequence(seq, seed=seed, **(oracle or ORACLE_NOISE))
    return Tracker.for_sequence(seq, TrackerConfig.from_dict(data), source), source


class RunCache:
    """Tracker runs shared between tests (each full run costs seconds)."""

    def __init__(self, seq: Sequence) -> None:
        self.seq = seq
        self.runs: dict[str, tuple] = {}

    def get(self, method: str, **config):
        if method not in self.runs:
            tracker, source = make_tracker(self.seq, method=method, **config)
            self.runs[method] = (tracker.track(self.seq), tracker, source)
        return self.runs[method]


@pytest.fixture(scope="session")
def runs(fast_sequence) -> RunCache:
    return RunCache(fast_sequence)


def stream(tracker: Tracker, seq: Sequence, rng: np.random.Generator | None = None,
           keep_frame=lambda i: True, drop_depth=lambda i: False, t_end_us: int | None = None):
    """Feed a sequence through the streaming API: events in random chunks, each frame once the
    events before it were pushed."""
    ev = seq.events
    if t_end_us is not None:
        ev = ev.between(0, t_end_us)
    times = seq.rgb_times_us.tolist()
    dtimes = seq.depth_times_us.tolist()
    frames = sorted({(t, "rgb", i) for i, t in enumerate(times)}
                    | {(t, "depth", i) for i, t in enumerate(dtimes)})
    pos = 0
    cuts = np.searchsorted(ev.t.numpy(), [f[0] for f in frames])
    for (t, kind, i), cut in zip(frames, cuts, strict=True):
        if t_end_us is not None and t >= t_end_us:
            break
        while pos < cut:
            n = int(rng.integers(1, 3000)) if rng is not None else cut - pos
            tracker.push_events(ev[pos:min(cut, pos + n)])
            pos = min(cut, pos + n)
        if not keep_frame(i):
            continue
        if kind == "rgb":
            tracker.push_frame(t, rgb=lambda i=i: seq.rgb(i))
        elif not drop_depth(i):
            tracker.push_frame(t, depth=seq.depth(i))
    if pos < len(ev):
        tracker.push_events(ev[pos:])
    tracker.advance(int(ev.t[-1]) + 1)
    tracker.flush()
    return tracker.trajectory()


__all__ = ["Path", "TEST_TRACKER", "make_tracker", "stream", "sim_config"]
