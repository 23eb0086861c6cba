"""Event Camera Dataset: the readers, the scene as the tracked object, ``evtrack import ecd``.

Most tests write format-true ECD folders in tmp_path (:mod:`ecd_folder`); those marked
``shared`` read the real cuts in ../shared/data/real.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from ecd_folder import SIZE, default_motion, write_ecd
from scipy.spatial.transform import Rotation

from evtrack.cli import main
from evtrack.datasets.ecd import (
    import_ecd,
    open_ecd,
    read_ecd_calib,
    read_ecd_groundtruth,
    read_ecd_images,
    read_ecd_motion,
)
from evtrack.errors import ConfigError, EventFileError
from evtrack.sequence import Sequence
from evtrack.sim.plane import facing_pose


# ---------------------------------------------------------------------------- readers
def test_calib_gives_opencv_camera(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", groundtruth=False)
    cam = read_ecd_calib(folder / "calib.txt")
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (199.092366542, 198.82882047, 132.192071378,
                                                110.712660011)
    assert cam.size == SIZE  # from the APS frames
    assert cam.dist.tolist() == [-0.368436311798, 0.150947243557, -0.000296130534385,
                                 -0.000759431726241, 0.0]
    assert read_ecd_calib(folder / "calib.txt", (320, 240)).size == (320, 240)


def test_sensor_size_comes_from_the_aps_frames(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", frame_size=(64, 48), groundtruth=False)
    assert read_ecd_calib(folder / "calib.txt").size == (64, 48)
    seq = Sequence.load(import_ecd(folder, tmp_path / "seq", plane_depth=0.5))
    assert seq.meta.event_camera.size == (64, 48) and seq.events.sensor_size == (64, 48)


def test_no_frames_and_no_size_says_to_pass_the_size(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", images=False, groundtruth=False)
    with pytest.raises(EventFileError) as err:
        read_ecd_calib(folder / "calib.txt")
    assert "--sensor-size W H" in str(err.value) and "240x180" in str(err.value)


def test_groundtruth_quaternion_is_scalar_last(tmp_path) -> None:
    R = Rotation.from_rotvec([0.3, -1.1, 0.7])
    qx, qy, qz, qw = R.as_quat(scalar_first=False)
    (tmp_path / "groundtruth.txt").write_text(
        f"0.5 1.0 2.0 3.0 {qx:.12f} {qy:.12f} {qz:.12f} {qw:.12f}\n")
    t_us, T_w_c = read_ecd_groundtruth(tmp_path / "groundtruth.txt")
    assert t_us.tolist() == [500_000] and t_us.dtype == torch.int64
    np.testing.assert_allclose(T_w_c[0, :3, :3].numpy(), R.as_matrix(), atol=1e-9)
    scalar_first = Rotation.from_quat([qx, qy, qz, qw], scalar_first=True).as_matrix()
    assert not np.allclose(T_w_c[0, :3, :3].numpy(), scalar_first, atol=1e-3)


def test_groundtruth_is_camera_to_world(tmp_path) -> None:
    """A point of the camera frame goes to R(q) P_c + p in the world; the camera's optical
    axis (its +z) points along R(q)'s third column."""
    R = Rotation.from_euler("y", 90.0, degrees=True)  # the camera looks along the world's +x
    qx, qy, qz, qw = R.as_quat(scalar_first=False)
    (tmp_path / "groundtruth.txt").write_text(f"0 1 2 3 {qx} {qy} {qz} {qw}\n")
    _, T_w_c = read_ecd_groundtruth(tmp_path / "groundtruth.txt")
    P_c = np.array([0.0, 0.0, 2.0, 1.0])  # 2 m ahead of the camera
    np.testing.assert_allclose((T_w_c[0].numpy() @ P_c)[:3], [1.0 + 2.0, 2.0, 3.0], atol=1e-9)


def test_images_and_motion_readers(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", groundtruth=False, motion_txt="0.5 -1.0 0.25")
    t_us, paths = read_ecd_images(folder / "images.txt")
    assert t_us.tolist() == [1_000_000, 1_025_000, 1_050_000, 1_075_000]
    assert [p.name for p in paths] == [f"frame_{k:08d}.png" for k in range(4)]
    assert all(p.parent == folder / "images" for p in paths)
    assert read_ecd_motion(folder / "motion.txt").tolist() == [0.5, -1.0, 0.25]


# ---------------------------------------------------------------------------- bad inputs
GT_LINE = "0.{k} 0 0 0 0 0 0 1"
BAD_INPUTS = {
    # name: (file, content, words the one-line message must hold)
    "calib count": ("calib.txt", "1 2 3 4 5 6 7 8", ["calib.txt", "line 1", "expected 9"]),
    "calib token": ("calib.txt", "200 200 x 110 0 0 0 0 0", ["line 1", "'cx'", "'x'"]),
    "calib focal": ("calib.txt", "-200 200 120 110 0 0 0 0 0", ["line 1", "'fx'", "positive"]),
    "calib lines": ("calib.txt", "200 200 120 110\n200 200 120 110", ["one line"]),
    "gt count": ("groundtruth.txt", "0.1 0 0 0 0 0 0 1\n0.2 0 0 0 0 0 1",
                 ["groundtruth.txt", "line 2", "expected 8 values"]),
    "gt token": ("groundtruth.txt", "0.1 0 0 0 0 0 0 1\n0.2 0 0 0 0 nan? 0 1",
                 ["line 2", "'qy'", "not a number"]),
    "gt nan": ("groundtruth.txt", "0.1 0 0 0 0 0 0 1\n0.2 0 nan 0 0 0 0 1",
               ["line 2", "'py'", "not finite"]),
    "gt time": ("groundtruth.txt", "0.1 0 0 0 0 0 0 1\n0.1s 0 0 0 0 0 0 1",
                ["line 2", "'t'"]),
    "gt unsorted": ("groundtruth.txt", "0.1 0 0 0 0 0 0 1\n# c\n0.3 0 0 0 0 0 0 1\n"
                    "0.2 0 0 0 0 0 0 1", ["line 4", "'t' goes back", "line 3"]),
    "gt repeated": ("groundtruth.txt", "0.1 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1",
                    ["line 2", "'t' repeats"]),
    "gt quaternion": ("groundtruth.txt", "0.1 0 0 0 0 0 0 1\n0.2 0 0 0 0.1 0 0 0.9",
                      ["line 2", "quaternion", "norm"]),
    "gt empty": ("groundtruth.txt", "# nothing\n", ["no poses"]),
    "images count": ("images.txt", "1.0 images/frame_00000000.png extra",
                     ["images.txt", "line 1", "expected 2 values"]),
    "images unsorted": ("images.txt", "1.05 images/frame_00000001.png\n"
                        "1.0 images/frame_00000000.png", ["images.txt", "line 2", "goes back"]),
    "events outside": ("events.txt", "1.0 10 10 1\n1.01 240 10 0",
                       ["events.txt", "line 2", "outside the sensor"]),
    "events token": ("events.txt", "1.0 10 10 1\n1.01 1O 10 0", ["events.txt", "line 2"]),
    "events unsorted": ("events.txt", "1.0 10 10 1\n0.5 11 10 0",
                        ["events.txt", "line 2", "backwards"]),
    "motion count": ("motion.txt", "0.1 0.2", ["motion.txt", "line 1", "expected 3 values"]),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_is_one_line_naming_file_line_and_field(tmp_path, case: str) -> None:
    name, content, words = BAD_INPUTS[case]
    folder = write_ecd(tmp_path / "rec", n_events=50)
    (folder / name).write_text(content + "\n")
    with pytest.raises(EventFileError) as err:
        import_ecd(folder, tmp_path / "seq", sensor_size=SIZE)
    message = str(err.value)
    assert "\n" not in message
    assert str(folder / name) in message
    for word in words:
        assert word in message, (word, message)
    assert not (tmp_path / "seq").exists()


def test_missing_calib_frame_and_events(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", n_events=50)
    (folder / "images" / "frame_00000002.png").unlink()
    with pytest.raises(EventFileError, match="frame_00000002.png: APS frame .* missing"):
        import_ecd(folder, tmp_path / "seq")
    (folder / "calib.txt").unlink()
    with pytest.raises(EventFileError, match=r"calib.txt: calibration file missing"):
        import_ecd(folder, tmp_path / "seq")
    no_events = write_ecd(tmp_path / "no_events", n_events=10)
    (no_events / "events.txt").unlink()
    with pytest.raises(EventFileError, match="events.txt: events file not found"):
        open_ecd(no_events)
    with pytest.raises(EventFileError, match="ECD folder not found"):
        open_ecd(tmp_path / "nothing-here")


def test_frames_of_another_size_than_the_sensor(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", frame_size=(64, 48), n_events=20)
    with pytest.raises(EventFileError, match=r"frame_00000000.png: APS frame is 64x48, the "
                                             r"sensor 240x180"):
        import_ecd(folder, tmp_path / "seq", sensor_size=SIZE)


# ---------------------------------------------------------------------------- the scene
def test_world_point_projects_where_the_camera_pose_says(tmp_path) -> None:
    """The scene's pose T_c_o(t) = inv(T_w_c(t)) @ T_w_o, checked against poses built
    independently with SciPy: a point fixed on the plane, seen by the camera at each
    ground-truth time, lands where the camera's own pose puts it."""
    motion = default_motion()
    folder = write_ecd(tmp_path / "rec", motion=motion)
    depth = 0.8
    seq = Sequence.load(import_ecd(folder, tmp_path / "seq", plane_depth=depth))
    gt = seq.ground_truth
    cam = seq.meta.event_camera
    t0 = 1.0
    # the plane faces the camera at the first event (on a ground-truth sample here)
    assert seq.meta.extra["start_t_us"] == 1_000_000
    np.testing.assert_allclose(seq.meta.extra["start_pose"], facing_pose(depth))
    np.testing.assert_allclose(gt.pose_at(1_000_000).numpy(), facing_pose(depth), atol=1e-9)
    p0, R0 = motion.pose(0.0)
    P_o = np.array([0.12, -0.05, 0.0])  # a point of the plane, object frame
    P_w = R0.apply(P_o + [0.0, 0.0, depth]) + p0  # where it is in the world
    for k, t_us in enumerate(gt.pose_t_us.tolist()):
        p, R = motion.pose(t_us * 1e-6 - t0)
        P_c_expected = R.inv().apply(P_w - p)
        P_c = gt.poses[k, :3, :3].numpy() @ P_o + gt.poses[k, :3, 3].numpy()
        np.testing.assert_allclose(P_c, P_c_expected, atol=1e-6)
        uv = cam.project(torch.from_numpy(P_c)).numpy()
        np.testing.assert_allclose(uv, cam.project(torch.from_numpy(P_c_expected)).numpy(),
                                   atol=1e-4)


@pytest.mark.parametrize("w_body, v_body", [((0.0, 0.8, 0.3), (0.0, 0.0, 0.0)),
                                            ((0.0, 0.0, 0.0), (0.3, 0.0, -0.1)),
                                            ((0.5, -0.2, 0.9), (0.2, 0.1, 0.0))])
def test_twist_is_the_scene_moving_opposite_to_the_camera(tmp_path, w_body, v_body) -> None:
    """A camera moving with v, w (its own frame) sees every static point move as
    dP/dt = -v - w x P: the scene's twist is [v_o, ω] = [-v, -w], in the package's
    convention (dP/dt = v_o + ω x P), and a finite difference of a scene point agrees."""
    motion = default_motion(w_body, v_body)
    folder = write_ecd(tmp_path / "rec", motion=motion)
    gt = Sequence.load(import_ecd(folder, tmp_path / "seq")).ground_truth
    expected = np.concatenate([-np.asarray(v_body), -np.asarray(w_body)])
    np.testing.assert_allclose(gt.twists.numpy(), np.broadcast_to(expected, gt.twists.shape),
                               atol=2e-4)
    T, t = gt.poses.numpy(), gt.pose_t_us.numpy() * 1e-6
    P_o = np.array([0.3, 0.2, 0.0])
    P = T[:, :3, :3] @ P_o + T[:, :3, 3]
    dP = (P[1:] - P[:-1]) / np.diff(t)[:, None]
    mid = (P[1:] + P[:-1]) / 2.0
    V = gt.twists.numpy()
    np.testing.assert_allclose(dP, V[:, :3] + np.cross(V[:, 3:], mid), atol=2e-3)


def test_without_groundtruth_the_scene_starts_facing_the_camera(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", groundtruth=False, motion_txt="0.5 -1.0 0.25")
    seq = Sequence.load(import_ecd(folder, tmp_path / "seq", plane_depth=0.6))
    assert seq.ground_truth is None
    np.testing.assert_allclose(seq.meta.extra["start_pose"], facing_pose(0.6))
    imu = seq.meta.extra["imu_angular_velocity"]
    assert imu["w_rad_s"] == [0.5, -1.0, 0.25] and "omega = -w" in imu["meaning"]


def test_scene_mesh_in_the_world_frame(tmp_path) -> None:
    from evtrack.geometry import inverse
    from evtrack.sim.objects import load_mesh, make_box

    mesh_file = tmp_path / "scene_box.glb"
    make_box(seed=3).export(mesh_file)
    motion = default_motion()
    folder = write_ecd(tmp_path / "rec", motion=motion)
    seq = Sequence.load(import_ecd(folder, tmp_path / "seq", scene_mesh=mesh_file))
    p0, R0 = motion.pose(0.0)
    T_w_c0 = np.eye(4)
    T_w_c0[:3, :3], T_w_c0[:3, 3] = R0.as_matrix(), p0
    np.testing.assert_allclose(seq.meta.extra["start_pose"],
                               inverse(torch.from_numpy(T_w_c0)).numpy(), atol=1e-9)
    copy = load_mesh(seq.mesh_file, recenter=False)
    np.testing.assert_allclose(np.sort(copy.extents), np.sort(make_box(seed=3).extents),
                               atol=1e-6)
    with pytest.raises(ConfigError, match="not both"):
        import_ecd(folder, tmp_path / "seq2", scene_mesh=mesh_file, plane_depth=1.0)


def test_plane_too_large_for_the_mesh_reader(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", n_events=20)
    with pytest.raises(ConfigError, match="lower --plane-depth"):
        import_ecd(folder, tmp_path / "seq", plane_depth=3.0)


def test_window_keeps_its_events_frames_and_covering_poses(tmp_path) -> None:
    folder = write_ecd(tmp_path / "rec", n_events=2000)
    seq = Sequence.load(import_ecd(folder, tmp_path / "seq", start_s=1.03, duration_s=0.04))
    t = seq.events.t
    assert int(t.min()) >= 1_030_000 and int(t.max()) < 1_070_000
    assert seq.rgb_times_us.tolist() == [1_050_000]
    gt_t = seq.ground_truth.pose_t_us
    assert int(gt_t[0]) <= int(t.min()) and int(gt_t[-1]) >= int(t.max())
    assert seq.meta.extra["start_t_us"] == int(t.min())
    with pytest.raises(EventFileError, match="no events in the window"):
        import_ecd(folder, tmp_path / "seq2", start_s=5.0, duration_s=1.0)
    with pytest.raises(ConfigError, match="needs its start"):
        import_ecd(folder, tmp_path / "seq2", duration_s=1.0)


# ---------------------------------------------------------------------------- the command
def test_evtrack_import_ecd_end_to_end(tmp_path, capsys) -> None:
    folder = write_ecd(tmp_path / "rec", n_events=1500, motion_txt="0 0.5 0")
    out = tmp_path / "seq"
    assert main(["import", "ecd", str(folder), "--out", str(out), "--plane-depth", "0.9"]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    seq = Sequence.load(out)
    events = np.loadtxt(folder / "events.txt")
    assert len(seq.events) == len(events)
    np.testing.assert_array_equal(seq.events.x.numpy(), events[:, 1].astype(int))
    np.testing.assert_array_equal(seq.events.p.numpy(), np.where(events[:, 3] > 0, 1, -1))
    assert seq.meta.rgb_camera == seq.meta.event_camera  # the APS frames: the same camera
    assert torch.equal(seq.meta.T_event_rgb, torch.eye(4, dtype=torch.float64))
    assert seq.num_rgb == 4 and seq.num_depth == 0
    rgb = seq.rgb(1)
    assert rgb.shape == (180, 240, 3) and (rgb[..., 0] == rgb[..., 2]).all()
    assert seq.meta.rates["rgb_hz"] == pytest.approx(40.0)
    assert seq.mesh_file.name == "scene.glb" and seq.mesh_file.is_file()
    assert seq.meta.extra["scene"]["depth_m"] == 0.9
    assert "APS frame at 1000000 µs" in seq.meta.extra["scene"]["texture"]
    # the folder exists already: one line, exit 1
    assert main(["import", "ecd", str(folder), "--out", str(out)]) == 1
    assert "exists" in capsys.readouterr().err
    # the plane or the mesh, not both
    with pytest.raises(SystemExit):
        main(["import", "ecd", str(folder), "--out", str(tmp_path / "x"), "--plane-depth",
              "1", "--scene-mesh", "m.glb"])


def test_evtrack_import_ecd_without_size_is_one_line(tmp_path, capsys) -> None:
    folder = write_ecd(tmp_path / "rec", n_events=20, images=False)
    assert main(["import", "ecd", str(folder), "--out", str(tmp_path / "seq")]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--sensor-size W H" in err
    assert main(["import", "ecd", str(folder), "--out", str(tmp_path / "seq"),
                 "--sensor-size", "240", "180"]) == 0


def test_tracker_for_the_imported_sequence(tmp_path) -> None:
    from evtrack import Tracker
    from evtrack.tracking.config import TrackerConfig

    folder = write_ecd(tmp_path / "rec", n_events=500)
    seq = Sequence.load(import_ecd(folder, tmp_path / "seq"))
    tracker = Tracker.for_sequence(seq, TrackerConfig(method="velocity"))
    assert tracker.camera == seq.meta.event_camera
    assert tracker.mesh is not None and len(tracker.mesh.faces) > 0
