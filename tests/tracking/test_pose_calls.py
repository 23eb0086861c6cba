"""Calls of the pose source (evtrack.tracking.pose_calls): the frames of its slots, the prior,
the worker thread and the counting of poses and misses."""

from __future__ import annotations

import threading

import numpy as np
import torch

from evtrack.tracking.pose_calls import FRAME_JITTER_US, PoseCaller
from evtrack.tracking.pose_sources import PoseMeasurement


class _Source:
    """Records its calls; a pose of confidence 0.9 on even frame times, else none."""

    accepts_prior = True

    def __init__(self) -> None:
        self.calls: list[tuple[int, bool, str]] = []

    def __call__(self, t_us, rgb, depth, prior=None):
        self.calls.append((t_us, prior is not None, threading.current_thread().name))
        if (t_us // 1000) % 2:
            return None
        return PoseMeasurement(t_us, torch.eye(4, dtype=torch.float64), confidence=0.9)


def test_frames_at_60_fps_take_the_5_hz_slots_within_the_jitter() -> None:
    caller = PoseCaller(_Source(), period_us=200_000, min_confidence=0.5)
    frames = np.round(np.arange(0, 1_000_000, 1e6 / 60)).astype(int) + 7  # µs off the grid
    taken = [int(t) for t in frames if caller.wants(int(t))]
    assert len(taken) == 5
    assert all(abs(t - 200_000 * i) <= FRAME_JITTER_US + 7 for i, t in enumerate(taken))
    early = PoseCaller(_Source(), period_us=200_000, min_confidence=0.5)
    assert early.wants(0) and early.wants(199_500) and not early.wants(200_000)
    early.reset()
    assert early.wants(200_000)  # slots start afresh


def test_calls_pass_a_prior_only_when_there_is_one_and_count_in_the_worker() -> None:
    source = _Source()
    caller = PoseCaller(source, period_us=200_000, min_confidence=0.5)
    assert caller.accepts_prior and not caller.uses_depth
    assert caller.call(0, np.zeros((2, 2, 3), np.uint8), None) is not None
    assert caller.call(2000, lambda: np.zeros((2, 2, 3), np.uint8), None, np.eye(4)) is not None
    assert [c[:2] for c in source.calls] == [(0, False), (2000, True)]
    futures = [caller.submit(t, np.zeros((2, 2, 3), np.uint8), None, None) for t in (4000, 5000)]
    results = [caller.result(f) for f in futures]
    assert caller.accepted(results[0]) and not caller.accepted(results[1])
    assert source.calls[-1][2].startswith("evtrack-pose")
    assert (caller.stats.poses, caller.stats.pose_misses) == (1, 1)
    low = PoseMeasurement(0, torch.eye(4, dtype=torch.float64), confidence=0.2)
    assert not caller.accepted(low) and not caller.accepted(None)
    assert caller.stats.time_s["pose_source"] > 0 and "pose_wait" in caller.stats.time_s
