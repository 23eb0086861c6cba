"""Depth refinement in the pose source, and the tracker handing depth frames to the sources that
ask for them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.models import RefineResult
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import NetworkPoseSource, PoseMeasurement
from evtrack.tracking.tracker import Tracker

CAM = PinholeCamera(100.0, 100.0, 31.5, 23.5, 64, 48)


class _Det:
    def __init__(self, pose: np.ndarray, confidence: float = 0.9) -> None:
        self.pose, self.confidence = torch.as_tensor(pose), confidence


class _StubRefiner:
    """Records its calls; moves the pose 1 cm along x, or refuses."""

    def __init__(self, refuse: bool = False) -> None:
        self.calls: list[tuple] = []
        self.refuse = refuse

    def refine(self, pose, depth, K, dist=None) -> RefineResult:
        self.calls.append((np.array(pose), depth, np.array(K)))
        out = np.array(pose, np.float64)
        if self.refuse:
            return RefineResult(out, False, 0, 0, float("nan"), 0, "no depth")
        out[0, 3] += 0.01
        return RefineResult(out, True, 100, 120, 1e-4, 5)


def _pose(z: float = 0.6) -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = z
    return T


def test_the_refined_pose_is_used_and_carried_into_the_event_camera() -> None:
    T_er = np.eye(4)
    T_er[1, 3] = 0.05
    refiner = _StubRefiner()
    src = NetworkPoseSource(lambda rgb: [_Det(_pose())], T_event_rgb=torch.from_numpy(T_er),
                            refiner=refiner, camera=CAM)
    assert src.uses_depth
    depth = np.full((48, 64), 0.6, np.float32)
    m = src(5, np.zeros((48, 64, 3), np.uint8), depth)
    expected = _pose()
    expected[0, 3] += 0.01
    np.testing.assert_allclose(m.pose.numpy(), T_er @ expected)
    assert refiner.calls[0][1] is depth
    np.testing.assert_allclose(refiner.calls[0][2], CAM.K().numpy())
    assert (src.refined, src.refine_refused) == (1, 0)
    # without a depth frame the network's pose goes through as it is
    m = src(6, np.zeros((48, 64, 3), np.uint8), None)
    np.testing.assert_allclose(m.pose.numpy(), T_er @ _pose())
    assert len(refiner.calls) == 1


def test_a_refused_refinement_keeps_the_network_pose() -> None:
    src = NetworkPoseSource(lambda rgb: [_Det(_pose())], refiner=_StubRefiner(refuse=True),
                            camera=CAM.K().numpy())
    m = src(5, np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.float32))
    np.testing.assert_allclose(m.pose.numpy(), _pose())
    assert (src.refined, src.refine_refused) == (0, 1)


def test_a_refiner_needs_the_camera() -> None:
    with pytest.raises(ConfigError, match="camera"):
        NetworkPoseSource(lambda rgb: [], refiner=_StubRefiner())
    assert not NetworkPoseSource(lambda rgb: []).uses_depth


class _RecordingSource:
    def __init__(self, uses_depth: bool, truth) -> None:
        self.uses_depth = uses_depth
        self.truth = truth
        self.seen: list = []

    def __call__(self, t_us, rgb, depth=None):
        self.seen.append((t_us, depth))
        return PoseMeasurement(t_us, self.truth(t_us))


@pytest.mark.parametrize("uses_depth", [True, False])
@pytest.mark.parametrize("depth_source", ["sensor", "model"])
def test_the_tracker_hands_depth_frames_to_sources_that_use_them(static_sequence, uses_depth,
                                                                 depth_source) -> None:
    seq = static_sequence
    source = _RecordingSource(uses_depth, seq.ground_truth.pose_at)
    cfg = TrackerConfig.from_dict({"method": "pose", "flow": {"roi_size": 16},
                                   "depth": {"source": depth_source}})
    Tracker.for_sequence(seq, cfg, source).track(seq)
    assert len(source.seen) >= 2
    times = seq.depth_times_us.tolist()
    for t_us, depth in source.seen:
        if uses_depth:
            np.testing.assert_array_equal(depth, seq.depth(times.index(t_us)))
        else:
            assert depth is None
