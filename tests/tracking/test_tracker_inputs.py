"""The streaming API's contract: input checks, fallbacks, loss and re-initialisation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError, EventsError
from evtrack.events import Events
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import PoseMeasurement
from evtrack.tracking.tracker import Tracker
from evtrack.tracking.trajectory import STATUS_LOST, STATUS_TRACKING, STATUS_WAITING

CAM = PinholeCamera(100.0, 100.0, 63.5, 47.5, 128, 96)
CUBE = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])


def _pose(x: float = 0.0, y: float = 0.0, z: float = 0.6) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _events(t, x=None, y=None) -> Events:
    n = len(t)
    x = np.full(n, 60) if x is None else x
    y = np.full(n, 40) if y is None else y
    return Events(x, y, t, np.ones(n), (128, 96))


def _tracker(**config) -> Tracker:
    """A tracker of the cube; step groups of 10 ms unless given (the tests below close
    groups with ``advance`` at multiples of 10 ms)."""
    return Tracker(TrackerConfig.from_dict({"flow_batch_steps": 10, **config}), camera=CAM,
                   mesh=CUBE)


def test_unsorted_events_are_an_error() -> None:
    tracker = _tracker()
    with pytest.raises(EventsError, match="go backwards"):
        tracker.push_events(_events([10, 5, 20]))


def test_events_before_earlier_ones_are_an_error() -> None:
    tracker = _tracker()
    tracker.push_events(_events([100, 200]))
    with pytest.raises(EventsError, match="before the last event"):
        tracker.push_events(_events([150]))
    tracker.advance(10_000)
    with pytest.raises(EventsError, match="clock"):
        tracker.push_events(_events([9_000]))


def test_events_outside_the_sensor_or_of_another_sensor() -> None:
    tracker = _tracker()
    with pytest.raises(EventsError):
        tracker.push_events(_events([1, 2], x=np.array([5, 200])))
    with pytest.raises(EventsError, match="sensor size"):
        tracker.push_events(Events([1], [1], [5], [1], (640, 480)))
    with pytest.raises(EventsError, match="sensor size"):  # empty, but of another sensor
        tracker.push_events(Events.empty((640, 480)))


def test_waiting_until_the_first_pose_then_tracking() -> None:
    tracker = _tracker(pose_latency_ms=0.0, flow_batch_steps=5)  # advance() closes 5 ms groups
    tracker.reset(t_us=0)
    tracker.advance(5_000)
    assert tracker.status == STATUS_WAITING
    assert np.isnan(tracker.pose()).all()
    tracker.push_pose(PoseMeasurement(5_000, _pose()))
    assert tracker.status == STATUS_TRACKING
    np.testing.assert_allclose(tracker.pose(), _pose(), atol=1e-12)
    traj = (tracker.advance(8_000), tracker.flush(), tracker.trajectory())[2]
    assert traj.status.tolist() == [0] * 5 + [1] * 3


def test_late_pose_is_fused_at_its_own_time() -> None:
    """A pose of t=20 ms pushed at 60 ms rolls the filter back: with zero twist the state equals
    the one reached by pushing the same pose on time."""
    on_time, late = _tracker(method="pose"), _tracker(method="pose")
    for tr in (on_time, late):
        tr.reset(_pose(), t_us=0)
    on_time.advance(20_000)
    on_time.push_pose(PoseMeasurement(20_000, _pose(x=0.01)))
    on_time.advance(60_000)
    late.advance(60_000)
    late.push_pose(PoseMeasurement(20_000, _pose(x=0.01)))
    np.testing.assert_allclose(late.pose(), on_time.pose(), atol=1e-12)
    torch.testing.assert_close(late.ukf.cov, on_time.ukf.cov)
    # the past outputs of the late tracker were not rewritten
    assert late.pose(30_000)[0, 3] == 0.0 and on_time.pose(30_000)[0, 3] > 0.0


def test_pose_older_than_the_history_is_dropped_and_counted() -> None:
    tracker = _tracker(method="pose", history_ms=500.0, pose_latency_ms=100.0)
    tracker.reset(_pose(), t_us=0)
    tracker.advance(1_000_000)
    tracker.push_pose(PoseMeasurement(100_000, _pose(x=0.01)))
    assert tracker.stats.poses_late == 1
    np.testing.assert_allclose(tracker.pose(), _pose(), atol=1e-12)


def test_frame_without_depth_uses_the_fallback_depth() -> None:
    """Sensor depth, but no depth frame ever: RoIs take the predicted depth of the object
    origin (counted), and the velocity filter still runs."""
    from evtrack.flow.scenes import translating_texture

    ev, _ = translating_texture((128, 96), velocity=(300.0, 0.0), duration_us=60_000)
    tracker = _tracker(flow={"roi_size": 16}, mask_margin_px=200.0)
    tracker.reset(_pose(), t_us=0)
    tracker.push_frame(0, rgb=None, depth=None)
    tracker.push_events(ev)
    tracker.flush()
    assert tracker.stats.frames_without_depth == 1
    assert tracker.stats.roi_flows > 0
    assert tracker.stats.depth_fallbacks == tracker.stats.roi_flows
    # a texture moving right at 300 px/s at depth 0.6 m: v_x ≈ 300 * 0.6 / 100 = 1.8 m/s
    assert tracker.twist()[0] > 0.5


def test_depth_frame_of_the_wrong_size_is_an_error() -> None:
    tracker = _tracker()
    with pytest.raises(ValueError, match="RGB-D camera"):
        tracker.push_frame(0, depth=np.ones((10, 10), np.float32))


def test_object_leaving_the_view_is_lost_then_reinitialised() -> None:
    tracker = _tracker(method="pose", lost_after_ms=20.0, pose_latency_ms=0.0)
    tracker.reset(_pose(x=5.0), t_us=0)  # far to the right: outside the image
    tracker.advance(30_000)
    assert tracker.status == STATUS_LOST and tracker.stats.lost == 1
    np.testing.assert_allclose(tracker.pose(), _pose(x=5.0), atol=1e-12)  # held
    tracker.push_pose(PoseMeasurement(30_000, _pose()))
    assert tracker.status == STATUS_TRACKING
    np.testing.assert_allclose(tracker.pose(), _pose(), atol=1e-12)
    traj = (tracker.advance(40_000), tracker.flush(), tracker.trajectory())[2]
    assert STATUS_LOST in traj.status.tolist() and traj.status[-1] == STATUS_TRACKING


def test_pose_source_rate_and_latency() -> None:
    calls = []

    def source(t_us, rgb, depth):
        calls.append(t_us)
        return PoseMeasurement(t_us, _pose())

    tracker = Tracker(TrackerConfig(pose_rate_hz=5.0, pose_latency_ms=100.0), camera=CAM,
                      mesh=CUBE, pose_source=source)
    rgb = np.zeros((96, 128, 3), np.uint8)
    for k in range(40):  # 60 FPS for 0.65 s
        tracker.push_frame(round(k * 1e6 / 60), rgb=rgb)
    assert calls == [0, 200_000, 400_000, 600_000]
    # the first pose (frame 0) reaches the filter at 100 ms
    traj = tracker.trajectory()
    first = int(traj.t_us[traj.tracked][0])
    assert first == 100_000


def test_model_depth_needs_a_mesh() -> None:
    with pytest.raises(ConfigError, match="mesh"):
        _tracker(depth={"source": "model"})


def test_track_command(fast_sequence, tmp_path, capsys) -> None:
    from evtrack.cli import main
    from evtrack.tracking.trajectory import Trajectory

    out = tmp_path / "pose.csv"
    code = main(["track", str(fast_sequence.root), "--out", str(out), "--method", "pose",
                 "--oracle", "--quiet"])
    assert code == 0
    text = capsys.readouterr().out
    assert "error against ground truth" in text
    traj = Trajectory.load(out)
    assert traj.method == "pose" and len(traj) > 500
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--oracle", "--quiet",
                 "--depth-range"]) == 0
    assert "depth ranges fused" in capsys.readouterr().out
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--oracle", "--quiet",
                 "--depth-icp"]) == 0
    text = capsys.readouterr().out
    assert "depth alignments fused" in text and "depth ranges" not in text
    assert main(["track", str(fast_sequence.root), "--out", str(out)]) == 1  # no pose source
    assert "--weights PATH" in capsys.readouterr().err
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--oracle",
                 "--oracle-noise", "-1", "0"]) == 1
    assert "--oracle-noise METRES RADIANS must be finite and >= 0" in capsys.readouterr().err
    # an output that cannot be written is refused before the tracking, not after it
    (tmp_path / "folder.csv").mkdir()
    (tmp_path / "file").write_text("")
    for bad, says in ((tmp_path / "folder.csv", "is a folder"),
                      (tmp_path / "file" / "x.csv", "is a file, not a folder")):
        assert main(["track", str(fast_sequence.root), "--out", str(bad), "--oracle"]) == 1
        captured = capsys.readouterr()
        assert says in captured.err and captured.out == ""  # no tracking summary


def test_a_lazy_frame_that_fails_raises_once_and_the_tracker_goes_on() -> None:
    """A depth frame given as a callable is read when its step comes: its error comes then,
    naming the frame, and the stream goes on (before, every later push failed on the flow's
    "events before the last batch")."""
    from evtrack.flow.scenes import translating_texture

    ev, _ = translating_texture((128, 96), velocity=(300.0, 0.0), duration_us=120_000)
    tracker = _tracker(flow={"roi_size": 16}, mask_margin_px=200.0)
    tracker.reset(_pose(), t_us=0)
    tracker.push_events(ev.between(0, 20_000))
    tracker.push_frame(25_000, depth=lambda: np.zeros((10, 10), np.float32))
    with pytest.raises(ValueError, match="t=25000 µs"):
        tracker.push_events(ev.between(20_000, 50_000))
    flows_before = tracker.stats.roi_flows
    for t0 in (50_000, 80_000):
        tracker.push_events(ev.between(t0, t0 + 30_000))
    tracker.flush()
    assert tracker.now_us >= 100_000
    assert tracker.stats.roi_flows > flows_before  # the flow still measures
    assert tracker.twist()[0] > 0.5  # and the filter still sees the texture move right


class _FixedSource:
    """A pose source that answers every frame with one pose (it reads the image it is given)."""

    def __call__(self, t_us, rgb, depth):
        assert rgb.shape == (96, 128, 3)
        return PoseMeasurement(t_us, _pose())


@pytest.mark.parametrize("rgb", [np.zeros((96, 128), np.uint8), np.zeros((96, 128, 3)),
                                 np.zeros((48, 64, 3), np.uint8), [[0, 0, 0]]])
def test_an_rgb_array_that_is_no_image_of_the_camera_is_refused_at_push_frame(rgb) -> None:
    tracker = Tracker(TrackerConfig(flow_batch_steps=10), camera=CAM, mesh=CUBE,
                      pose_source=_FixedSource())
    with pytest.raises(ValueError, match="RGB frame at t=5000 µs"):
        tracker.push_frame(5_000, rgb=rgb)
    assert tracker.stats.frames == 0  # nothing queued
    tracker.push_frame(6_000, rgb=np.zeros((96, 128, 3), np.uint8))
    tracker.advance(220_000)  # past the pose's 200 ms latency
    assert tracker.status == STATUS_TRACKING


def test_a_lazy_rgb_frame_of_the_wrong_size_names_its_time_and_the_tracker_goes_on() -> None:
    tracker = Tracker(TrackerConfig(pose_async=False, pose_latency_ms=0.0, flow_batch_steps=10),
                      camera=CAM, mesh=CUBE, pose_source=_FixedSource())
    tracker.push_frame(5_000, rgb=lambda: np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="RGB frame at t=5000 µs is 64x48"):
        tracker.advance(20_000)
    tracker.push_frame(205_000, rgb=lambda: np.zeros((96, 128, 3), np.uint8))
    tracker.advance(220_000)
    assert tracker.status == STATUS_TRACKING


def test_rgb_is_not_read_nor_checked_when_nothing_uses_it() -> None:
    tracker = _tracker()  # full method, no pose source
    tracker.push_frame(5_000, rgb=np.zeros((3, 3), np.uint8))
    assert tracker.stats.frames == 1


def test_an_older_depth_frame_does_not_replace_the_newer_one() -> None:
    tracker = _tracker()
    tracker.reset(_pose(), t_us=0)
    tracker.push_frame(100_000, depth=np.full((96, 128), 0.6, np.float32))
    tracker.advance(130_000)
    assert tracker.roi_depth.source.t_us == 100_000
    tracker.push_frame(60_000, depth=np.full((96, 128), np.nan, np.float32))
    assert tracker.roi_depth.source.t_us == 100_000
    assert float(np.nanmax(tracker.roi_depth.source.map)) == pytest.approx(0.6)
    tracker.push_frame(140_000, depth=np.full((96, 128), 0.7, np.float32))
    tracker.advance(150_000)
    assert tracker.roi_depth.source.t_us == 140_000


@pytest.mark.parametrize(("pose", "match"), [
    (np.full((4, 4), np.nan), "not finite"),
    (2 * np.eye(4), "not a rotation"),
    (np.eye(3), r"\(4, 4\)"),
    ("identity", "array of numbers"),
])
def test_reset_refuses_a_pose_that_is_not_rigid_and_keeps_the_track(pose, match) -> None:
    tracker = _tracker(method="pose")
    tracker.reset(_pose(), t_us=0)
    tracker.advance(10_000)
    with pytest.raises(ValueError, match=f"reset: starting pose at t=20000 µs.*{match}"):
        tracker.reset(pose, t_us=20_000)
    assert tracker.status == STATUS_TRACKING and tracker.now_us == 10_000


def test_a_network_of_another_object_is_warned_about(fast_sequence) -> None:
    import warnings

    from evtrack.tracking.pose_sources import NetworkPoseSource

    class _Estimator:
        camera = None

        def __init__(self, object_name: str) -> None:
            self.object_name = object_name

        def __call__(self, rgb):
            return []

    assert fast_sequence.meta.object_name == "box"
    with pytest.warns(UserWarning, match="trained for 'coded_box'.*object is 'box'"):
        Tracker.for_sequence(fast_sequence, TrackerConfig(),
                             NetworkPoseSource(_Estimator("coded_box")))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Tracker.for_sequence(fast_sequence, TrackerConfig(), NetworkPoseSource(_Estimator("box")))


def test_track_command_says_when_nothing_was_tracked_or_depth_was_missing(
        fast_sequence, tmp_path, capsys, monkeypatch) -> None:
    import shutil

    import cv2

    import evtrack.cli.track as track_cli
    from evtrack.cli import main

    seq = tmp_path / "seq"
    shutil.copytree(fast_sequence.root, seq)
    for png in (seq / "depth").glob("*.png"):  # a depth camera that sees nothing
        cv2.imwrite(str(png), np.zeros_like(cv2.imread(str(png), cv2.IMREAD_UNCHANGED)))
    assert main(["track", str(seq), "--out", str(tmp_path / "a.csv"), "--oracle",
                 "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "took the fallback" in captured.err and "error against ground truth" in captured.out
    monkeypatch.setattr(track_cli, "_pose_source", lambda args, seq: lambda t, rgb, d: None)
    assert main(["track", str(fast_sequence.root), "--out", str(tmp_path / "b.csv"),
                 "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "no sample was tracked" in out and "nan" not in out


def test_events_behind_the_clock_name_the_call_that_moved_it() -> None:
    tracker = _tracker()
    tracker.push_events(_events([100, 200]))
    tracker.push_frame(10_000_000)  # a frame stamped by another clock
    with pytest.raises(EventsError, match=r"moved there by push_frame\(t_us=10000000\)"):
        tracker.push_events(_events([300]))
    tracker = _tracker()
    tracker.push_events(_events([100, 200]))
    tracker.advance(50_000)
    with pytest.raises(EventsError, match=r"moved there by advance\(t_us=50000\)"):
        tracker.push_events(_events([300]))
