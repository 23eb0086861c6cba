"""Pose sources (evtrack.tracking.pose_sources): the noisy oracle and the network source
(best detection, alternatives, pose prior)."""

from __future__ import annotations

import numpy as np
import torch
from tracker_helpers import rigid_pose

from evtrack.tracking.pose_sources import NetworkPoseSource, OraclePoseSource


def test_oracle_is_deterministic_per_frame_and_noisy() -> None:
    truth = rigid_pose([0.1, 0.2, 0.3], [0.0, 0.0, 0.6])
    src = OraclePoseSource(lambda t: torch.from_numpy(truth), std_translation=0.01,
                           std_rotation=0.02, seed=5)
    a = [src(t) for t in range(0, 100_000, 1000)]
    b = [src(t) for t in reversed(range(0, 100_000, 1000))][::-1]
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x.pose, y.pose)
    dt = np.array([(m.pose[:3, 3].numpy() - truth[:3, 3]) for m in a])
    assert 0.006 < dt.std() < 0.014
    out = OraclePoseSource(lambda t: torch.from_numpy(truth), outlier_rate=1.0, seed=1)(7)
    assert np.linalg.norm(out.pose[:3, 3].numpy() - truth[:3, 3]) > 0
    assert OraclePoseSource(lambda t: torch.from_numpy(truth), dropout_rate=1.0)(7) is None


def test_network_source_takes_the_best_detection_into_the_event_camera() -> None:
    class Det:
        def __init__(self, pose, c):
            self.pose, self.confidence = pose, c

    T_er = rigid_pose([0, 0.1, 0], [0.05, 0, 0])
    dets = [Det(rigid_pose([0, 0, 0], [0, 0, 1.0]), 0.4),
            Det(rigid_pose([0, 0, 0.2], [0, 0.1, 0.8]), 0.9)]
    src = NetworkPoseSource(lambda rgb: dets, T_event_rgb=torch.from_numpy(T_er),
                            min_confidence=0.5)
    m = src(10, np.zeros((8, 8, 3), np.uint8))
    np.testing.assert_allclose(m.pose.numpy(), T_er @ dets[1].pose)
    assert m.confidence == 0.9
    assert NetworkPoseSource(lambda rgb: dets, min_confidence=0.95)(0, None) is None
    assert m.alternatives == ()  # detections without alternatives give none


def test_network_source_hands_on_the_detections_alternatives() -> None:
    """A detection's alternatives become the measurement's, mapped into the event camera like
    the pose; those below ``min_confidence`` are left out, invalid ones counted."""
    class Det:
        def __init__(self, pose, c, alternatives=()):
            self.pose, self.confidence, self.alternatives = pose, c, alternatives

    T_er = rigid_pose([0, 0.1, 0], [0.05, 0, 0])
    sheared = rigid_pose([0, 0, 0], [0, 0, 1.0])
    sheared[0, 1] = 0.5  # not a rotation
    alts = (Det(rigid_pose([0.1, 0, 0], [0, 0, 0.9]), 0.6), Det(sheared, 0.55),
            Det(rigid_pose([0, 0.2, 0], [0, 0, 1.1]), 0.3))
    src = NetworkPoseSource(lambda rgb: [Det(rigid_pose([0, 0, 0.2], [0, 0.1, 0.8]), 0.9, alts)],
                            T_event_rgb=torch.from_numpy(T_er), min_confidence=0.5)
    m = src(10, np.zeros((8, 8, 3), np.uint8))
    (alt,) = m.alternatives
    np.testing.assert_allclose(alt.pose.numpy(), T_er @ alts[0].pose)
    assert alt.t_us == 10 and alt.confidence == 0.6 and src.invalid == 1


def test_network_source_hands_the_prior_to_the_estimator_in_the_rgb_camera() -> None:
    """With a prior (event camera frame), an estimator with ``estimate_near`` gets it in its
    own (RGB) camera frame; without one, or for a plain callable, the whole-image call."""
    class Det:
        def __init__(self, pose, c):
            self.pose, self.confidence, self.alternatives = pose, c, ()

    class Estimator:
        def __init__(self):
            self.calls = []

        def __call__(self, rgb):
            self.calls.append(("image", None))
            return [Det(rigid_pose([0, 0, 0], [0, 0, 1.0]), 0.9)]

        def estimate_near(self, rgb, prior):
            self.calls.append(("near", prior))
            return [Det(prior, 0.8)]

    T_er = rigid_pose([0, 0.1, 0], [0.05, 0, 0])
    est = Estimator()
    src = NetworkPoseSource(est, T_event_rgb=torch.from_numpy(T_er))
    assert src.accepts_prior
    prior_event = rigid_pose([0.2, -0.1, 0.3], [0.02, 0.01, 0.7])
    m = src(10, np.zeros((8, 8, 3), np.uint8), None, prior=prior_event)
    (kind, got), = est.calls
    assert kind == "near"
    np.testing.assert_allclose(got, np.linalg.inv(T_er) @ prior_event, atol=1e-12)
    np.testing.assert_allclose(m.pose.numpy(), prior_event, atol=1e-12)  # back in the event frame
    src(20, np.zeros((8, 8, 3), np.uint8))
    assert est.calls[-1] == ("image", None)
    plain = NetworkPoseSource(lambda rgb: [Det(rigid_pose([0, 0, 0], [0, 0, 1.0]), 0.9)])
    assert plain(0, None, prior=prior_event).pose[2, 3] == 1.0
