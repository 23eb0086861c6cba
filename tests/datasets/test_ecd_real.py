"""The real ECD cuts of ../shared/data/real: read, imported, and tracked."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evtrack.datasets.ecd import DAVIS240C_SIZE, import_ecd, open_ecd, read_ecd_groundtruth
from evtrack.errors import EventFileError
from evtrack.sequence import Sequence

pytestmark = pytest.mark.shared


@pytest.fixture(scope="module")
def real_dir(shared_dir: Path) -> Path:
    path = shared_dir / "data" / "real"
    if not path.is_dir():
        pytest.skip(f"{path} is absent: the real ECD recordings are missing")
    return path


def test_slider_groundtruth_and_frames(real_dir: Path) -> None:
    rec = open_ecd(real_dir / "ecd_slider_depth")
    assert rec.camera.size == DAVIS240C_SIZE  # from its APS frames
    assert rec.events_path.name == "events_chunk.txt"
    t_us, T_w_c = read_ecd_groundtruth(real_dir / "ecd_slider_depth" / "groundtruth.txt")
    assert len(t_us) == 339 and int(t_us[0]) == 22292
    np.testing.assert_allclose(T_w_c[:, :3, :3].numpy(), np.broadcast_to(np.eye(3), (339, 3, 3)))
    assert len(rec.image_paths) == 87  # listed; the cut keeps the first 7 files


def test_slider_scene_slides_along_minus_x(real_dir: Path, tmp_path: Path) -> None:
    """The camera slides along its +x at ~0.3 m/s with no rotation: the scene's twist is
    v_o ≈ (-0.3, 0, 0) m/s, ω = 0."""
    with pytest.warns(UserWarning, match="not all of the imported"):  # poses start at 22 ms
        out = import_ecd(real_dir / "ecd_slider_depth", tmp_path / "slider")
    seq = Sequence.load(out)
    V = seq.ground_truth.twists.numpy()
    assert 0.25 < -np.median(V[:, 0]) < 0.36
    np.testing.assert_allclose(V[:, 1:], 0.0, atol=1e-6)
    assert seq.num_rgb == 4 and len(seq.events) == 50_000
    assert "APS frame" in seq.meta.extra["scene"]["texture"]


def test_rotation_sample_needs_the_sensor_size(real_dir: Path) -> None:
    # its 000000000.png is a 480x540 mosaic of visualisations, not an APS frame: no images.txt
    with pytest.raises(EventFileError, match="--sensor-size W H"):
        open_ecd(real_dir / "ecd_shapes_rotation_sample")


def _tracked(seq: Sequence, config):
    """A :class:`~evtrack.Tracker` of ``config`` run over an imported ECD sample from its
    imported start pose."""
    from evtrack import Tracker

    tracker = Tracker.for_sequence(seq, config)
    extra = seq.meta.extra
    tracker.reset(np.asarray(extra["start_pose"]), t_us=extra["start_t_us"])
    for chunk in seq.iter_events(window_us=50_000):
        tracker.push_events(chunk)
    tracker.flush()
    return tracker


def test_tracker_on_an_imported_rotation_sample(real_dir: Path, tmp_path: Path) -> None:
    """The default tracker (method velocity, started from the imported pose) follows the
    scene's turn: its mean angular velocity over the second half points along -w of the IMU,
    and its steps stay near it. The imported plane is a scene around the camera, so the
    velocity noise has no pivot (with the plane's centre as pivot: RMSE 0.49 rad/s)."""
    from evtrack.tracking.config import TrackerConfig

    seq = Sequence.load(import_ecd(real_dir / "ecd_shapes_rotation_sample", tmp_path / "shapes",
                                   sensor_size=DAVIS240C_SIZE))
    assert len(seq.events) == 20_000 and seq.ground_truth is None
    tracker = _tracked(seq, TrackerConfig(method="velocity"))
    extra = seq.meta.extra
    traj = tracker.trajectory()
    assert len(traj.t_us) >= 95 and bool((traj.status == 1).all())
    omega = traj.twists.numpy()[len(traj.t_us) // 2:, 3:]
    assert np.isfinite(omega).all()
    ref = -np.asarray(extra["imu_angular_velocity"]["w_rad_s"])
    mean = omega.mean(0)
    cos = mean @ ref / (np.linalg.norm(mean) * np.linalg.norm(ref))
    assert cos > 0.95, (mean, ref)
    rmse = float(np.sqrt(((omega - ref) ** 2).sum(1).mean()))
    assert rmse < 0.35, rmse
    assert tracker.motion.is_scene_at(np.asarray(extra["start_pose"]))


def test_line_less_flows_are_refused_where_they_dominate(real_dir: Path, tmp_path: Path) -> None:
    """On the slow poster clip most RoI windows report one unconfirmed candidate: judged
    strictly (the default ``flow.max_lineless_share``), the tracker's angular velocity points
    along -w at its magnitude; taking them (share 1) overestimates it by about two thirds."""
    from evtrack.tracking.config import TrackerConfig

    seq = Sequence.load(import_ecd(real_dir / "ecd_poster_rotation_sample", tmp_path / "poster",
                                   sensor_size=DAVIS240C_SIZE))
    ref = -np.asarray(seq.meta.extra["imu_angular_velocity"]["w_rad_s"])
    default = TrackerConfig().flow.max_lineless_share
    assert default < 1.0
    results = {}
    for share in (default, 1.0):
        traj = _tracked(seq, TrackerConfig.from_dict(
            {"method": "velocity", "flow": {"max_lineless_share": share}})).trajectory()
        mean = traj.twists.numpy()[len(traj.t_us) // 2:, 3:].mean(0)
        cos = float(mean @ ref / (np.linalg.norm(mean) * np.linalg.norm(ref)))
        results[share] = (cos, float(np.linalg.norm(mean) / np.linalg.norm(ref)))
    strict, loose = results[default], results[1.0]
    assert strict[0] > 0.95 and 0.8 < strict[1] < 1.25, results
    assert loose[1] > 1.4, results


def test_evtrack_track_from_the_imported_start_pose(real_dir: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture) -> None:
    """'evtrack track --method velocity --start-pose' tracks an imported ECD cut with no pose
    source, as the Python API does, and the same trajectory comes out."""
    from evtrack import Tracker
    from evtrack.cli import main
    from evtrack.tracking.config import TrackerConfig

    folder = import_ecd(real_dir / "ecd_shapes_rotation_sample", tmp_path / "shapes",
                        sensor_size=DAVIS240C_SIZE)
    out = tmp_path / "t.h5"
    assert main(["track", str(folder), "--method", "velocity", "--start-pose", "--out",
                 str(out), "--quiet"]) == 0
    seq = Sequence.load(folder)
    extra = seq.meta.extra
    want = Tracker.for_sequence(seq, TrackerConfig(method="velocity")).track(
        seq, start_pose=np.asarray(extra["start_pose"]), start_t_us=extra["start_t_us"])
    assert bool((want.status == 1).all()) and len(want.t_us) >= 95
    from evtrack.tracking.trajectory import Trajectory

    got = Trajectory.load(out)
    np.testing.assert_array_equal(got.t_us.numpy(), want.t_us.numpy())
    np.testing.assert_allclose(got.twists.numpy(), want.twists.numpy(), rtol=0, atol=0)
    capsys.readouterr()
    assert main(["track", str(folder), "--out", str(tmp_path / "u.h5"), "--quiet"]) == 1
    assert "--start-pose" in capsys.readouterr().err


def test_start_pose_missing_from_the_sequence(tmp_path: Path, capsys) -> None:
    from evtrack.cli import main

    seq_dir = tmp_path / "seq"
    _tiny_sequence(seq_dir)
    assert main(["track", str(seq_dir), "--method", "velocity", "--start-pose", "--out",
                 str(tmp_path / "t.h5"), "--quiet"]) == 1
    assert "has no extra.start_pose" in capsys.readouterr().err


def _tiny_sequence(folder: Path) -> None:
    from evtrack.camera import PinholeCamera
    from evtrack.events import Events
    from evtrack.sequence import SequenceMeta, SequenceWriter

    meta = SequenceMeta(PinholeCamera(100, 100, 20, 15, 40, 30), mesh_path=None)
    with SequenceWriter(folder, meta) as w:
        w.add_events(Events([1, 2], [3, 4], [10, 20], [1, -1], (40, 30)))
