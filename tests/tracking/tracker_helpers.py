"""Helpers shared by the tracker tests (imported by conftest.py and the test modules)."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from evtrack import Sequence
from evtrack.camera import PinholeCamera
from evtrack.events import Events
from evtrack.sim.config import EventConfig, GroundTruthConfig, SimConfig, TrajectoryConfig
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import OraclePoseSource
from evtrack.tracking.tracker import Tracker

# Tracker settings of the accuracy tests: RoIs sized for 128x96 images, poses at 10 Hz
# arriving 100 ms late (the 0.6 s sequence then holds 6 poses), GE contrast = the threshold.
# Small simulated images (the defaults' pixel sizes are stated for 640x480): 16 px RoIs and an
# 8 px mask margin, the settings the bounds and measured numbers of these tests were made with.
TEST_TRACKER = {"flow": {"roi_size": 16}, "mask_margin_px": 8.0, "pose_rate_hz": 10.0,
                "pose_latency_ms": 100.0, "ge": {"contrast": 0.5}}
ORACLE_NOISE = {"std_translation": 0.01, "std_rotation": 0.03}

#: a small camera of the unit tests of the tracker's parts
SMALL_CAM = PinholeCamera(120.0, 110.0, 79.5, 59.5, 160, 120)


def rigid_pose(rotvec, t) -> np.ndarray:
    """(4, 4) float64 pose from a rotation vector (rad) and a translation (m)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def sim_config(duration: float, seed: int) -> SimConfig:
    cfg = SimConfig(duration=duration, seed=seed, trajectory=TrajectoryConfig(preset="faster"),
                    events=EventConfig(threshold_on=0.5, threshold_off=0.5),
                    ground_truth=GroundTruthConfig(event_flow=False))
    return dataclasses.replace(cfg, camera=cfg.camera.resized(128, 96))


def make_tracker(seq: Sequence, seed: int = 0, oracle: dict | None = None,
                 **config) -> tuple[Tracker, OraclePoseSource]:
    """A tracker for ``seq`` with a noisy oracle pose source and the test settings."""
    data = {**TEST_TRACKER, **config}
    source = OraclePoseSource.from_sequence(seq, seed=seed, **(oracle or ORACLE_NOISE))
    return Tracker.for_sequence(seq, TrackerConfig.from_dict(data), source), source


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


def record_flow_calls(tracker: Tracker) -> list[tuple[int, int, int, int]]:
    """Wrap the tracker's flow: record (events, first t, last t, events searched) of every
    call."""
    calls: list[tuple[int, int, int, int]] = []
    update = tracker.motion.flow.update

    def recorded(ev: Events, **kwargs):
        search = kwargs.get("search")
        calls.append((len(ev), int(ev.t[0]) if len(ev) else -1, int(ev.t[-1]) if len(ev) else -1,
                      len(ev) if search is None else int(search.sum())))
        return update(ev, **kwargs)

    tracker.motion.flow.update = recorded
    return calls
