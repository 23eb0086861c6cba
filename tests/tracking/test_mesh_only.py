"""``pose_source: model``: the tracker corrects its pose with the object's mesh alone (depth
alignment and appearance alignment), nothing trained; and its bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from tracker_helpers import TEST_TRACKER, stream

import evtrack
from evtrack.errors import ConfigError
from evtrack.eval.metrics import tracking_errors
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import OraclePoseSource
from evtrack.tracking.tracker import Tracker


def _start(seq):
    gt = seq.ground_truth
    t0 = int(gt.pose_t_us[0])
    return gt.pose_at(t0), t0


def _tracker(seq, **config) -> Tracker:
    return Tracker.for_sequence(seq, TrackerConfig.from_dict({**TEST_TRACKER, **config}))


@pytest.fixture(scope="module")
def mesh_runs(fast_sequence):
    """The fast box sequence from its true first pose: the events alone (``velocity``), the
    mesh with RGB-D frames, and the mesh with the RGB frames only."""
    pose, t0 = _start(fast_sequence)
    out = {}
    for name, config in (("velocity", {"method": "velocity"}),
                         ("rgbd", {"pose_source": "model"}),
                         ("rgb", {"pose_source": "model", "depth": {"source": "model"}})):
        tracker = _tracker(fast_sequence, **config)
        traj = tracker.track(fast_sequence, start_pose=pose, start_t_us=t0)
        out[name] = (tracking_errors(traj, fast_sequence.ground_truth), tracker, traj)
    return out


def test_the_mesh_alone_corrects_the_event_track(mesh_runs) -> None:
    """With the RGB-D frames the mesh holds the track near the truth (measured 0.79 cm /
    1.72°); the events alone drift (4.69 cm / 23.9°)."""
    rgbd, tracker, _ = mesh_runs["rgbd"]
    velocity = mesh_runs["velocity"][0]
    assert rgbd.samples == velocity.samples > 500
    assert rgbd.position_rmse_cm < 1.5 and rgbd.rotation_rmse_deg < 4.0
    assert rgbd.position_rmse_cm < 0.4 * velocity.position_rmse_cm
    assert rgbd.rotation_rmse_deg < 0.25 * velocity.rotation_rmse_deg
    st = tracker.stats
    # ICP on every depth frame (30 Hz), appearance at 10 Hz, over 0.6 s; no pose source
    assert st.depth_alignments >= 12 and st.appearance_alignments >= 4
    assert st.poses == st.pose_calls == 0
    assert "appearance" in st.time_s and "depth_icp" in st.time_s


def test_rgb_frames_alone_also_correct_it(mesh_runs) -> None:
    """Without depth frames (the RoIs' depth rendered from the mesh) the appearance alone
    still corrects the drift (measured 1.84 cm / 4.83°)."""
    rgb, tracker, _ = mesh_runs["rgb"]
    velocity = mesh_runs["velocity"][0]
    assert rgb.rotation_rmse_deg < 8.0 and rgb.position_rmse_cm < 3.0
    assert rgb.rotation_rmse_deg < 0.4 * velocity.rotation_rmse_deg
    assert tracker.stats.depth_alignments == 0 and tracker.depth_fusion is None
    assert tracker.stats.appearance_alignments >= 4


def test_streaming_equals_offline(fast_sequence, mesh_runs) -> None:
    """The live API (events in random chunks, frames as they come) gives the offline track."""
    _, _, offline = mesh_runs["rgbd"]
    pose, t0 = _start(fast_sequence)
    tracker = _tracker(fast_sequence, pose_source="model")
    tracker.reset(pose, t0)
    online = stream(tracker, fast_sequence, np.random.default_rng(3))
    np.testing.assert_array_equal(online.t_us.numpy(), offline.t_us.numpy())
    np.testing.assert_array_equal(online.poses.numpy(), offline.poses.numpy())


def test_an_empty_depth_frame_is_counted_and_the_rgb_frame_still_used(
        fast_sequence, monkeypatch) -> None:
    """Depth frames with no valid pixel (all zero): every alignment on them is refused and
    counted by reason; the appearance alignments go on."""
    monkeypatch.setattr(fast_sequence, "depth",
                        lambda i: np.zeros((96, 128), np.float32))
    pose, t0 = _start(fast_sequence)
    tracker = _tracker(fast_sequence, pose_source="model")
    traj = tracker.track(fast_sequence, start_pose=pose, start_t_us=t0)
    st = tracker.stats
    assert st.depth_alignments == 0 and sum(st.depth_alignments_skipped.values()) >= 12
    assert set(st.depth_alignments_skipped) == {"few depth pixels"}
    assert st.appearance_alignments >= 4
    assert bool(traj.tracked.all())


def test_nothing_happens_without_a_start_pose(fast_sequence) -> None:
    """The mesh corrects a pose; it does not find one: without a start pose the track waits
    (global registration is not part of it)."""
    tracker = _tracker(fast_sequence, pose_source="model")
    traj = tracker.track(fast_sequence)
    assert not bool(traj.tracked.any())
    assert tracker.stats.appearance_alignments == tracker.stats.depth_alignments == 0


def test_a_start_pose_behind_the_camera_is_refused(fast_sequence) -> None:
    """A start pose with the object behind the camera (a camera-to-object pose, say) is an
    error before anything is reset; the tracker keeps its state."""
    pose, t0 = _start(fast_sequence)
    tracker = _tracker(fast_sequence, pose_source="model")
    tracker.reset(pose, t0)
    behind = np.linalg.inv(pose.numpy())
    assert behind[2, 3] < 0
    with pytest.raises(ValueError, match="behind the event camera"):
        tracker.reset(behind, t0)
    assert tracker.initialized
    with pytest.raises(ValueError, match="behind the event camera"):
        tracker.track(fast_sequence, start_pose=behind, start_t_us=t0)


def test_config_and_input_errors(fast_sequence) -> None:
    with pytest.raises(ConfigError, match="'velocity' method takes poses only to start"):
        TrackerConfig.from_dict({"pose_source": "model", "method": "velocity"})
    with pytest.raises(ConfigError, match="pose_source: must be one of"):
        TrackerConfig.from_dict({"pose_source": "mesh"})
    source = OraclePoseSource.from_sequence(fast_sequence)
    with pytest.raises(ConfigError, match="pose source \\(OraclePoseSource\\) was given"):
        Tracker.for_sequence(fast_sequence, TrackerConfig(pose_source="model"), source)
    tracker = _tracker(fast_sequence, pose_source="model")
    with pytest.raises(ConfigError, match="pass none"):
        tracker.pose_source = source
    vertices = np.random.default_rng(0).normal(size=(50, 3)) * 0.05
    with pytest.raises(ConfigError, match="pose_source: model needs the object's mesh"):
        Tracker(TrackerConfig(pose_source="model"), camera=fast_sequence.meta.event_camera,
                mesh=vertices)
    with pytest.raises(ConfigError, match="appearance.enabled needs the object's mesh"):
        Tracker(TrackerConfig(appearance={"enabled": True}),
                camera=fast_sequence.meta.event_camera, mesh=vertices)


def test_the_config_flags(fast_sequence) -> None:
    """``pose_source: model`` turns on both alignments (the depth one only with sensor depth);
    ``appearance.enabled`` adds the appearance to a network's poses."""
    model = TrackerConfig(pose_source="model")
    assert model.uses_appearance and model.uses_depth_icp
    rgb = TrackerConfig(pose_source="model", depth={"source": "model"})
    assert rgb.uses_appearance and not rgb.uses_depth_icp
    both = TrackerConfig(appearance={"enabled": True})
    assert both.uses_appearance and not both.uses_depth_icp
    plain = TrackerConfig()
    assert not plain.uses_appearance and not plain.uses_depth_icp
    # barely seen ICP directions count as unseen where the appearance measures them
    assert model.icp_min_information == both.icp_min_information == 0.01
    assert plain.icp_min_information == TrackerConfig(depth_fusion={"icp": True}
                                                      ).icp_min_information == 0.0
    assert TrackerConfig(pose_source="model", depth_fusion={"icp_min_information": 0.0}
                         ).icp_min_information == 0.0
    tracker = Tracker.for_sequence(fast_sequence, plain)
    assert tracker.appearance is None


def _silhouette_box(seq, t_us: int) -> tuple[int, int, int, int]:
    """A box 3 px around the object's projection at its true pose of ``t_us``."""
    T = np.linalg.inv(seq.meta.T_event_rgb.numpy()) @ seq.ground_truth.pose_at(t_us).numpy()
    from evtrack.sim.objects import load_mesh

    V = load_mesh(seq.mesh_file, recenter=False).vertices.astype(np.float64)
    X = V @ T[:3, :3].T + T[:3, 3]
    cam = seq.meta.rgb_camera
    u, v = cam.fx * X[:, 0] / X[:, 2] + cam.cx, cam.fy * X[:, 1] / X[:, 2] + cam.cy
    return int(u.min()) - 3, int(v.min()) - 3, int(u.max()) + 4, int(v.max()) + 4


def _assert_started_near_truth(tracker: Tracker, seq, t_us: int) -> None:
    """The tracker's pose is within 2° and 5 mm of the truth at ``t_us``."""
    truth = seq.ground_truth.pose_at(t_us).numpy()
    R = tracker.pose()[:3, :3].T @ truth[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 2.0
    assert np.linalg.norm(tracker.pose()[:3, 3] - truth[:3, 3]) < 0.005


def test_the_start_is_found_on_the_first_frame(fast_sequence, mesh_runs, tmp_path,
                                               capsys) -> None:
    """``start_from_frame`` registers the mesh on the first RGB-D frame (a box around the
    object given) and starts the track there; ``evtrack track --start-box`` does the same."""
    from evtrack.cli import main

    t0 = int(fast_sequence.rgb_times_us[0])
    box = _silhouette_box(fast_sequence, t0)
    from evtrack.models import RegistrationConfig

    tracker = _tracker(fast_sequence, pose_source="model")
    found = tracker.start_from_frame(t0, fast_sequence.rgb(0), fast_sequence.depth(0), box,
                                     RegistrationConfig(rotations=32))
    _assert_started_near_truth(tracker, fast_sequence, t0)
    assert found.correlation > 0.9 and tracker.initialized and tracker.now_us == t0
    config = tmp_path / "tracker.yaml"
    config.write_text("flow: {roi_size: 16}\nmask_margin_px: 8.0\n")
    out = tmp_path / "t.csv"
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--mesh-only",
                 "--config", str(config), "--start-box", *map(str, box), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "start pose registered on the frame at" in printed and "appearance alignments" in printed
    err = tracking_errors(evtrack.Trajectory.load(out), fast_sequence.ground_truth)
    assert err.rotation_rmse_deg < 1.5 * mesh_runs["rgbd"][0].rotation_rmse_deg + 0.5
    from_truth = tmp_path / "from_truth.csv"
    assert main(["track", str(fast_sequence.root), "--out", str(from_truth), "--mesh-only",
                 "--config", str(config), "--start-from-ground-truth", "--quiet"]) == 0
    truth_start = tracking_errors(evtrack.Trajectory.load(from_truth),
                                  fast_sequence.ground_truth)
    assert truth_start.rotation_rmse_deg < 4.0 and truth_start.samples > 500
    with pytest.raises(ValueError, match="holds no part"):
        tracker.start_from_frame(t0, fast_sequence.rgb(0), fast_sequence.depth(0),
                                 (500, 500, 600, 600))
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--mesh-only",
                 "--start-box", *map(str, box), "--start-from-ground-truth", "--quiet"]) == 1
    assert "give one start" in capsys.readouterr().err


def test_the_start_is_found_without_a_box(fast_sequence, mesh_runs, tmp_path, capsys) -> None:
    """Without a box the object is looked for where the depth stands out of the scene's
    planes (``find_mesh``): the same start as with the box; ``evtrack track --start-find``."""
    from evtrack.cli import main
    from evtrack.models import RegistrationConfig, find_mesh

    t0 = int(fast_sequence.rgb_times_us[0])
    tracker = _tracker(fast_sequence, pose_source="model")
    found = tracker.start_from_frame(t0, fast_sequence.rgb(0), fast_sequence.depth(0), None,
                                     RegistrationConfig(rotations=32))
    _assert_started_near_truth(tracker, fast_sequence, t0)
    su0, sv0, su1, sv1 = _silhouette_box(fast_sequence, t0)
    u0, v0, u1, v1 = found.box
    overlap = max(0, min(u1, su1) - max(u0, su0)) * max(0, min(v1, sv1) - max(v0, sv0))
    assert overlap > 0.7 * (su1 - su0) * (sv1 - sv0)
    assert found.correlation > 0.9 and tracker.now_us == t0

    config = tmp_path / "tracker.yaml"
    config.write_text("flow: {roi_size: 16}\nmask_margin_px: 8.0\n")
    out = tmp_path / "t.csv"
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--mesh-only",
                 "--config", str(config), "--start-find", "--quiet"]) == 0
    assert "in the box" in capsys.readouterr().out
    err = tracking_errors(evtrack.Trajectory.load(out), fast_sequence.ground_truth)
    assert err.rotation_rmse_deg < 1.5 * mesh_runs["rgbd"][0].rotation_rmse_deg + 0.5

    mesh = tracker.mesh
    empty = np.zeros_like(fast_sequence.depth(0))
    with pytest.raises(ValueError, match="no valid pixel"):
        find_mesh(mesh, fast_sequence.meta.rgb_camera, fast_sequence.rgb(0), empty)
    millimetres = dataclasses.replace(mesh, vertices=mesh.vertices * 1000.0)
    with pytest.raises(ValueError, match="mesh in metres"):
        find_mesh(millimetres, fast_sequence.meta.rgb_camera, fast_sequence.rgb(0),
                  fast_sequence.depth(0))
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--mesh-only",
                 "--start-find", "--start-from-ground-truth", "--quiet"]) == 1
    assert "give one start" in capsys.readouterr().err
