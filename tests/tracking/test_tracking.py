"""End-to-end tracking on small simulated sequences, with the oracle pose source.

Bounds were measured on these exact sequences (seeded) and set with a margin; the comments give
the values measured when the test was written.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tracker_helpers import make_tracker, stream

from evtrack.errors import ConfigError
from evtrack.eval.metrics import tracking_errors
from evtrack.filters import VelocityKF
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import PoseMeasurement
from evtrack.tracking.trajectory import STATUS_TRACKING, STATUS_WAITING


def _same(a, b) -> None:
    assert torch.equal(a.t_us, b.t_us)
    assert torch.equal(a.status, b.status)
    torch.testing.assert_close(a.poses, b.poses, rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(a.twists, b.twists, rtol=0, atol=0, equal_nan=True)


def test_streaming_equals_offline(fast_sequence, runs) -> None:
    offline, _, _ = runs.get("full")
    tracker, _ = make_tracker(fast_sequence, method="full")
    online = stream(tracker, fast_sequence, np.random.default_rng(7))
    _same(offline, online)
    # one sample per 1 ms step, waiting until the first (late) pose, then tracking
    assert np.all(np.diff(offline.t_us.numpy()) == 1000)
    assert offline.status[0] == STATUS_WAITING and offline.status[-1] == STATUS_TRACKING
    assert bool(torch.isfinite(offline.poses[offline.tracked]).all())


def test_full_beats_velocity_and_pose(fast_sequence, runs) -> None:
    gt = fast_sequence.ground_truth
    err = {m: tracking_errors(runs.get(m)[0], gt) for m in ("full", "velocity", "pose")}
    full, vel, pose = err["full"], err["velocity"], err["pose"]
    # measured: full 5.8 cm / 15.5 deg, velocity 7.1 / 24.6, pose 12.1 / 13.7; after the box
    # got one hue per face (a different event stream): full 4.2 / 14.8, velocity 5.0 / 23.6,
    # so the position margin over velocity is 10% (it was 15%). The event twist
    # corrects the position between poses; the rotation about the object's own centre is
    # weakly observable from its flow, so the full method's rotation stays near the poses'
    # (as in the paper's tables).
    assert full.samples == vel.samples == pose.samples > 450
    assert full.position_rmse_cm < 0.9 * vel.position_rmse_cm
    assert full.position_rmse_cm < 0.6 * pose.position_rmse_cm
    assert full.position_rmse_cm < 7.0
    assert full.rotation_rmse_deg < 0.75 * vel.rotation_rmse_deg
    assert full.rotation_rmse_deg < 1.3 * pose.rotation_rmse_deg


def test_pose_outliers_are_gated(fast_sequence, runs) -> None:
    """10% of the poses replaced by random ones (30 Hz poses: 18 of them)."""
    noise = {"std_translation": 0.01, "std_rotation": 0.03}
    tracker, source = make_tracker(fast_sequence, method="full", pose_rate_hz=30.0,
                                   oracle={**noise, "outlier_rate": 0.1}, seed=10)
    traj = tracker.track(fast_sequence)
    latency = 100_000
    first = int(traj.t_us[traj.tracked][0]) - latency  # frame time of the first fused pose
    last = int(traj.t_us[-1]) - latency  # later poses arrive after the end
    outliers = [t for t in source.outliers if first < t <= last]
    assert len(outliers) >= 2
    # every outlier, no inlier: by the gate or, before it, by the depth check
    assert tracker.stats.poses_rejected + tracker.stats.poses_implausible == len(outliers)
    assert tracker.stats.reinitialisations == 0
    err = tracking_errors(traj, fast_sequence.ground_truth)
    # measured: 4.85 cm / 11.9 deg with the outliers, 4.80 / 11.7 with the same poses and no
    # outliers; with a third of the poses (10 Hz, no outliers): 5.8 / 15.5
    assert err.position_rmse_cm < 5.5 and err.rotation_rmse_deg < 14.0
    clean_10hz = tracking_errors(runs.get("full")[0], fast_sequence.ground_truth)
    assert err.position_rmse_cm < clean_10hz.position_rmse_cm


def test_dropped_frames_and_missing_depth(fast_sequence, runs) -> None:
    """A third of the RGB frames dropped, half of the depth frames missing."""
    tracker, _ = make_tracker(fast_sequence, method="full")
    traj = stream(tracker, fast_sequence, keep_frame=lambda i: i % 3 != 1,
                  drop_depth=lambda i: i % 2 == 1)
    err = tracking_errors(traj, fast_sequence.ground_truth)
    clean = tracking_errors(runs.get("full")[0], fast_sequence.ground_truth)
    # measured: 5.8 cm / 15.8 deg, as with every frame (5.8 / 15.5)
    assert tracker.stats.poses >= 4
    assert err.position_rmse_cm < clean.position_rmse_cm + 2.0
    assert err.rotation_rmse_deg < clean.rotation_rmse_deg + 5.0


def test_at_rest_twist_decays_and_pose_holds(fast_sequence) -> None:
    """Events stop at 0.35 s (the object stops emitting): the twist decays, the pose holds."""
    tracker, _ = make_tracker(fast_sequence, method="full", pose_latency_ms=0.0)
    stream(tracker, fast_sequence, t_end_us=350_000)
    moving = np.linalg.norm(tracker.twist())
    tracker.advance(600_000)
    tracker.flush()
    traj = tracker.trajectory()
    late = traj.t_us >= 400_000
    assert moving > 0.05
    assert np.linalg.norm(tracker.twist()) < 1e-9
    poses = traj.poses[late]
    assert float((poses - poses[0]).abs().max()) < 1e-9


def test_static_object_stays_put(static_sequence) -> None:
    """No events at all; noisy poses at 10 Hz: the estimate stays within the pose noise."""
    tracker, _ = make_tracker(static_sequence, method="full", pose_latency_ms=0.0)
    traj = tracker.track(static_sequence)
    assert tracker.stats.events == 0
    assert float(traj.twists.abs().max()) == 0.0
    err = tracking_errors(traj, static_sequence.ground_truth)
    # one pose: 1 cm per axis (1.73 cm RMS), 0.03 rad per axis (2.98 deg RMS); measured
    # 2.1 cm / 3.0 deg (the filter holds the last pose, weighted towards it)
    assert err.position_rmse_cm < 1.5 * 1.73 and err.rotation_rmse_deg < 1.5 * 2.98


@pytest.mark.parametrize("method", ["frame-flow", "ge"])
def test_other_baselines_track(fast_sequence, runs, method) -> None:
    traj, tracker, _ = runs.get(method)
    err = tracking_errors(traj, fast_sequence.ground_truth)
    pose = tracking_errors(runs.get("pose")[0], fast_sequence.ground_truth)
    assert err.samples == pose.samples
    # measured: frame-flow 7.8 cm / 16.9 deg, ge 11.1 / 14.4 (pose 12.1 / 13.7)
    assert err.position_rmse_cm < 2.0 * pose.position_rmse_cm
    assert err.rotation_rmse_deg < 2.0 * pose.rotation_rmse_deg
    if method == "frame-flow":
        assert tracker.stats.twist_measurements > 20
    else:
        assert tracker.stats.velocity_updates > 300


def _first_100_ms_errors(traj, traj_plain, seq):
    """Tracking errors of two runs over the first 100 ms of tracking, which both start at
    the same step."""
    start = int(traj.t_us[traj.status == 1][0])
    assert start == int(traj_plain.t_us[traj_plain.status == 1][0])
    window = {"t_start_us": start, "t_end_us": start + 100_000}
    return (tracking_errors(traj, seq.ground_truth, **window),
            tracking_errors(traj_plain, seq.ground_truth, **window))


def test_frame_flow_measures_the_frames_a_late_first_pose_missed(fast_sequence, runs,
                                                                 monkeypatch) -> None:
    """The first pose arrives 100 ms after its frame: the frame pairs since then are measured
    at the timeline's poses, carrying that pose to the present (as the event flow does)."""
    traj, tracker, _ = runs.get("frame-flow")
    assert tracker.stats.twists_replayed > 0
    plain, _ = make_tracker(fast_sequence, method="frame-flow")
    monkeypatch.setattr(plain.motion, "track_started", lambda t_pose: None)
    with_replay, without = _first_100_ms_errors(traj, plain.track(fast_sequence),
                                                fast_sequence)
    # measured over the first 100 ms: 5.2 cm with the replay, 13.9 cm without
    assert with_replay.position_rmse_cm < 0.6 * without.position_rmse_cm


def test_event_flow_measures_again_the_steps_a_late_first_pose_missed(fast_sequence,
                                                                     runs) -> None:
    """remeasure.on_pose (default): once the first pose (100 ms late) starts the track, the
    steps since its frame, measured on all events without a pose, are measured again at the
    timeline's poses (RoIs in the silhouette, depths in its range, the object as pivot)."""
    traj, tracker, _ = runs.get("full")
    assert tracker.stats.steps_remeasured > 50  # measured: 80 of the 100 steps
    plain, _ = make_tracker(fast_sequence, method="full", remeasure={"on_pose": False})
    traj_plain = plain.track(fast_sequence)
    assert plain.stats.steps_remeasured == 0
    again, without = _first_100_ms_errors(traj, traj_plain, fast_sequence)
    # measured over the first 100 ms: 5.6 cm / 21.3 deg measured again, 6.4 cm / 26.3 without
    assert again.rotation_rmse_deg < 0.9 * without.rotation_rmse_deg
    assert again.position_rmse_cm < without.position_rmse_cm


def _first_pose_shifted(source, metres: float):
    """``source`` with its first pose moved ``metres`` along the camera's x axis."""
    shifted = []

    def call(t_us, rgb, depth):
        m = source(t_us, rgb, depth)
        if m is not None and not shifted:
            shifted.append(t_us)
            pose = m.pose.clone()
            pose[0, 3] += metres
            m = PoseMeasurement(m.t_us, pose, m.cov, m.confidence)
        return m

    return call


@pytest.mark.parametrize("depth_source", ["sensor", "model"])
def test_a_first_pose_that_misses_the_events_is_not_used_to_measure_again(fast_sequence,
                                                                         depth_source) -> None:
    """A first pose 6 cm off (about 20 px on the 128x96 image) leaves many RoI flows
    outside its silhouette: the kept steps keep their unposed twists (remeasure_min_inside),
    and the run equals one with remeasure_on_pose off. With model depth the check looks at a
    shorter span (the unposed steps hold the pose still), and still finds it off."""
    tracker, source = make_tracker(fast_sequence, method="full", depth={"source": depth_source})
    tracker.pose_source = _first_pose_shifted(source, 0.06)
    traj = tracker.track(fast_sequence)
    assert tracker.stats.remeasures_skipped == 1 and tracker.stats.steps_remeasured == 0
    plain, plain_source = make_tracker(fast_sequence, method="full", remeasure={"on_pose": False},
                                       depth={"source": depth_source})
    plain.pose_source = _first_pose_shifted(plain_source, 0.06)
    _same(traj, plain.track(fast_sequence))
    with pytest.raises(ConfigError, match="remeasure: min_inside"):
        TrackerConfig(remeasure={"min_inside": 1.5})


def test_velocity_noise_pivots_about_the_tracked_object(fast_sequence, runs) -> None:
    """velocity_kf.object_centred (default): the velocity filter's process noise is set about
    the object's current position (off: the paper's diagonal noise)."""
    _, tracker, _ = runs.get("full")
    Q = tracker.motion.vkf.q_matrix
    p = torch.from_numpy(tracker.pose()[:3, 3])
    expected = VelocityKF(tracker.camera)
    expected.set_pivot(p)  # about the final pose; Q was set at the last step's predicted pose
    torch.testing.assert_close(Q, expected.q_matrix, rtol=0.02, atol=1.0)
    assert float(Q[:3, 3:].abs().max()) > 0
    plain, _ = make_tracker(fast_sequence, method="full", velocity_kf={"object_centred": False})
    plain.track(fast_sequence)
    assert torch.equal(plain.motion.vkf.q_matrix, torch.diag(plain.motion.vkf.q_density))


def test_a_scene_around_the_camera_has_no_pivot(fast_sequence) -> None:
    """An object whose radius is at least ``pivot_max_radius_ratio`` of its distance is taken
    for a scene around the camera (a moving camera's recording): the velocity noise then has
    no pivot. The test's box (radius ~0.12 m) is an object at 1 m and a scene at 0.2 m, or
    at 1 m with a ratio of 0.1."""
    tracker, _ = make_tracker(fast_sequence, method="full")
    motion = tracker.motion
    radius = motion.object_radius_m
    assert 0.05 < radius < 0.2

    def pose_at(distance):
        T = np.eye(4)
        T[:3, 3] = (0.0, 0.0, distance)
        return T

    assert not motion.is_scene_at(pose_at(1.0)) and motion.is_scene_at(pose_at(0.2))
    assert motion.is_scene_at(pose_at(radius / 0.5 - 1e-6))
    assert not motion.is_scene_at(pose_at(radius / 0.5 + 1e-6))
    diag = torch.diag(motion.vkf.q_density)
    motion.segment_started(pose_at(1.0))
    assert float(motion.vkf.q_matrix[:3, 3:].abs().max()) > 0  # pivots on the object
    motion.segment_started(pose_at(0.2))
    assert torch.equal(motion.vkf.q_matrix, diag)
    near, _ = make_tracker(fast_sequence, method="full", pivot_max_radius_ratio=0.1)
    near.motion.segment_started(pose_at(1.0))
    assert torch.equal(near.motion.vkf.q_matrix, diag)
    with pytest.raises(ConfigError, match="pivot_max_radius_ratio"):
        TrackerConfig(pivot_max_radius_ratio=0.0)


def test_model_depth_tracks_like_sensor_depth(fast_sequence, runs) -> None:
    """Depth rendered from the mesh at the predicted pose instead of the sensor's. Before the
    first pose there is no model depth: the steps only keep their RoI flows, measured once
    the late first pose is there (remeasure_on_pose), so compare after 0.3 s."""
    tracker, _ = make_tracker(fast_sequence, method="full", depth={"source": "model"})
    traj = tracker.track(fast_sequence)
    gt = fast_sequence.ground_truth
    err = tracking_errors(traj, gt, t_start_us=300_000)
    ref = tracking_errors(runs.get("full")[0], gt, t_start_us=300_000)
    print(f"after 0.3 s: model {err.position_rmse_cm:.2f} cm / {err.rotation_rmse_deg:.2f} deg, "
          f"sensor {ref.position_rmse_cm:.2f} / {ref.rotation_rmse_deg:.2f}")
    # measured after 0.3 s: model 4.44 cm / 8.73 deg, sensor 4.17 / 8.21 (2026-11-27; 6.7 /
    # 10.9 and 5.9 / 8.4 without measuring the model's steps before the first pose again).
    # Model depth is taken at the predicted pose, so a pose error also scales the velocity.
    # A RoI on the silhouette's edge can miss the model's silhouette rendered at a predicted
    # pose a little off: 1 of 3214 RoI flows with llvmpipe's default sampling, 3 of 3037 with
    # its bilinear-LOD sampling (GALLIVM_PERF=brilinear), whose renders differ in last bits.
    assert tracker.roi_depth.source.renders > 50
    assert tracker.stats.depth_fallbacks <= 0.01 * tracker.stats.roi_flows, tracker.stats
    assert err.position_rmse_cm < 1.4 * ref.position_rmse_cm
    assert err.rotation_rmse_deg < ref.rotation_rmse_deg + 3.5


def test_model_depth_measures_the_steps_a_late_first_pose_missed(fast_sequence) -> None:
    """With model depth the steps before the first pose (100 ms late) keep their RoI flows
    and are measured once that pose is there, with the mesh rendered at the timeline's poses
    (the filter holds the pose still over them otherwise)."""
    tracker, _ = make_tracker(fast_sequence, method="full", depth={"source": "model"})
    traj = tracker.track(fast_sequence)
    assert tracker.stats.steps_remeasured > 50
    plain, _ = make_tracker(fast_sequence, method="full", depth={"source": "model"},
                            remeasure={"on_pose": False})
    traj_plain = plain.track(fast_sequence)
    assert plain.stats.steps_remeasured == 0
    assert plain.stats.roi_flows < tracker.stats.roi_flows
    again, without = _first_100_ms_errors(traj, traj_plain, fast_sequence)
    print(f"first 100 ms: measured again {again.position_rmse_cm:.2f} cm / "
          f"{again.rotation_rmse_deg:.2f} deg, without {without.position_rmse_cm:.2f} / "
          f"{without.rotation_rmse_deg:.2f}")
    # measured: 4.09 cm / 20.23 deg measured again, 12.07 / 21.89 without (2026-11-27)
    assert again.position_rmse_cm < 0.5 * without.position_rmse_cm
    assert again.rotation_rmse_deg < without.rotation_rmse_deg + 1.0
