"""The pose gate (evtrack.tracking.pose_gate), without a tracker: the depth frame of a pose's
time, the depth check against a synthetic depth map, alternatives, half turns in a row, and the
agreement of two gated poses."""

from __future__ import annotations

import numpy as np
import torch
from tracker_helpers import SMALL_CAM, rigid_pose

from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_flips import HalfTurnResolver, half_turn
from evtrack.tracking.pose_gate import PoseGate
from evtrack.tracking.pose_sources import PoseMeasurement
from evtrack.tracking.silhouette import Silhouette

CUBE = np.array([[x, y, z] for x in (-.1, .1) for y in (-.1, .1) for z in (-.1, .1)])
AT_HALF_METRE = rigid_pose([0, 0, 0], [0, 0, 0.5])


def _gate(half_turns: HalfTurnResolver | None = None, **config) -> PoseGate:
    cfg = TrackerConfig.from_dict({"history_ms": 100.0, "depth": {"max_age_ms": 20.0},
                                  "pose_latency_ms": 0.0, "pose_rate_hz": 20.0, **config})
    return PoseGate(cfg, Silhouette(CUBE, SMALL_CAM), sensor_depth=True, aligner=None,
                    half_turns=half_turns)


def _measurement(T: np.ndarray, t_us: int = 0, confidence: float = 1.0,
                 alternatives=()) -> PoseMeasurement:
    return PoseMeasurement(t_us, torch.from_numpy(T), confidence=confidence,
                           alternatives=list(alternatives))


def _plane(z_m: float) -> np.ndarray:
    return np.full((SMALL_CAM.height, SMALL_CAM.width), z_m, np.float32)


def test_the_depth_frame_of_a_pose_is_the_nearest_within_the_age() -> None:
    gate = _gate()
    for t in (0, 30_000, 60_000, 90_000, 120_000):
        gate.remember_depth(t, _plane(t * 1e-6))
    assert sorted(gate.depth_frames) == [30_000, 60_000, 90_000, 120_000]  # history_ms
    assert gate.frame_depth(44_000)[0, 0] == np.float32(0.03)
    assert gate.frame_depth(45_000)[0, 0] == np.float32(0.03)  # as near: the earlier
    assert gate.frame_depth(5_000) is None  # 0 is forgotten, 30 ms is beyond 20 ms


def test_a_pose_the_depth_contradicts_is_dropped_and_an_alternative_taken() -> None:
    gate = _gate()
    gate.remember_depth(0, _plane(0.5))  # the cube spans 0.4 to 0.6 m in depth
    right = _measurement(AT_HALF_METRE)
    far = rigid_pose([0, 0, 0], [0, 0, 1.0])
    assert gate.checked(right) is right
    assert gate.checked(_measurement(far)) is None
    assert gate.stats.poses_implausible == 1
    alts = [_measurement(far, confidence=0.9), _measurement(AT_HALF_METRE, confidence=0.2),
            _measurement(AT_HALF_METRE, confidence=0.8)]
    taken = gate.checked(_measurement(far, alternatives=alts))
    assert taken is alts[2]  # the first confirmed one above both confidence floors
    assert gate.stats.poses_from_alternatives == 1 and gate.stats.poses_implausible == 1
    off = _gate(pose_gate={"alternatives": False})
    off.remember_depth(0, _plane(0.5))
    assert off.checked(_measurement(far, alternatives=alts)) is None


def test_without_a_depth_frame_of_its_time_a_pose_passes() -> None:
    gate = _gate()
    gate.remember_depth(0, _plane(0.5))
    far = _measurement(rigid_pose([0, 0, 0], [0, 0, 1.0]), t_us=50_000)
    assert gate.checked(far) is far


def test_half_turns_turn_the_pose_then_reinitialise_after_enough_in_a_row() -> None:
    resolver = HalfTurnResolver("z", np.zeros(3), max_view_deg=30.0)
    gate = _gate(resolver, pose_gate={"half_turn_reinit_after": 3})
    turned = AT_HALF_METRE @ half_turn(2, np.zeros(3))
    m = _measurement(turned)
    for _ in range(2):
        out, reinit = gate.nearer_half_turn(m, AT_HALF_METRE)
        assert not reinit and np.allclose(out.pose.numpy(), AT_HALF_METRE)
    out, reinit = gate.nearer_half_turn(m, AT_HALF_METRE)
    assert reinit and out is m  # the third in a row: the track is deemed off
    assert gate.stats.poses_half_turned == 2 and gate.stats.half_turn_reinits == 1
    out, reinit = gate.nearer_half_turn(_measurement(AT_HALF_METRE), AT_HALF_METRE)
    assert not reinit and gate.half_turns_in_row == 0
    assert gate.nearer_half_turn(m, None) == (m, False)  # no reference pose: as it is


def test_a_pose_agreeing_with_the_gated_one_reinitialises() -> None:
    gate = _gate()
    first = _measurement(AT_HALF_METRE, t_us=0)
    near = torch.from_numpy(rigid_pose([0, 0, 0.05], [0.01, 0, 0.5]))
    assert not gate.agrees_with_rejected(100_000, near)  # nothing gated yet
    gate.fused(first, rejected=True)
    assert gate.agrees_with_rejected(100_000, near)
    assert not gate.agrees_with_rejected(100_000, torch.from_numpy(
        rigid_pose([0, 0, 0], [0.5, 0, 0.5])))
    gate.fused(first, rejected=False)
    assert not gate.agrees_with_rejected(100_000, near)
    off = _gate(pose_gate={"reinit_on_agreement": False})
    off.fused(first, rejected=True)
    assert not off.agrees_with_rejected(100_000, near)
