"""Plots (written, non-empty, binned values against brute force) and the overlay video."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from evtrack import Sequence
from evtrack.camera import PinholeCamera
from evtrack.eval.plots import (
    SpeedErrors,
    binned_rmse,
    euler_degrees,
    plot_error_vs_speed,
    plot_tracking_curves,
)
from evtrack.eval.samples import pixel_speed_at, sample_errors
from evtrack.eval.video import (
    cuboid_segments,
    project_segments,
    wireframe_segments,
    write_overlay_video,
)
from evtrack.sim.objects import procedural_object
from evtrack.tracking.trajectory import STATUS_TRACKING, STATUS_WAITING, Trajectory

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def gt_trajectory(seq: Sequence, offset_m: float = 0.0, waiting: int = 0) -> Trajectory:
    """Ground truth sampled at 1 kHz (shifted along x by ``offset_m``); the first ``waiting``
    samples are not tracked."""
    gt = seq.ground_truth
    t = torch.arange(int(gt.pose_t_us[0]), int(gt.pose_t_us[-1]), 1000)
    poses = gt.pose_at(t).clone()
    poses[:, 0, 3] += offset_m
    status = torch.full((len(t),), STATUS_TRACKING, dtype=torch.int8)
    status[:waiting] = STATUS_WAITING
    return Trajectory(t, poses, torch.zeros(len(t), 6), status, "test")


def assert_png(path):
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 5000


def test_binned_rmse_matches_a_loop():
    rng = np.random.default_rng(0)
    speed = rng.uniform(0, 100, 2000)
    error = rng.normal(0, 1 + speed / 50)
    edges = np.linspace(0, 100, 11)
    centres, got = binned_rmse(speed, error, edges, min_samples=5)
    for b in range(10):
        sel = [i for i in range(len(speed)) if edges[b] <= speed[i] < edges[b + 1]
               or (b == 9 and speed[i] == edges[-1])]
        assert got[b] == pytest.approx(np.sqrt(np.mean(error[sel] ** 2)))
        assert centres[b] == pytest.approx((edges[b] + edges[b + 1]) / 2)
    # sparse bins are left out
    _, sparse = binned_rmse(speed[:30], error[:30], edges, min_samples=20)
    assert np.isnan(sparse).all()


def test_euler_degrees_unwraps_and_keeps_gaps():
    angles = np.linspace(0, 400, 81)
    poses = np.tile(np.eye(4), (81, 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("z", angles[:, None], degrees=True).as_matrix()
    poses[40] = np.nan
    out = euler_degrees(poses)
    assert np.isnan(out[40]).all()
    keep = np.arange(81) != 40
    np.testing.assert_allclose(out[keep, 2], angles[keep], atol=1e-6)
    np.testing.assert_allclose(out[keep, :2], 0, atol=1e-6)


def test_tracking_curves_and_error_plot_are_written(tiny_benchmark, tmp_path):
    seq = Sequence.load(tiny_benchmark / "box_faster")
    trajs = {"exact": gt_trajectory(seq, waiting=50), "shifted": gt_trajectory(seq, 0.02)}
    err = sample_errors(trajs["shifted"], seq.ground_truth)
    np.testing.assert_allclose(err.position_cm, 2.0, atol=1e-9)
    np.testing.assert_allclose(err.rotation_deg, 0.0, atol=1e-5)
    assert len(sample_errors(trajs["exact"], seq.ground_truth).t_us) == len(trajs["exact"]) - 50
    speed = pixel_speed_at(err.t_us, seq.ground_truth, procedural_object("box", 0).vertices,
                           seq.meta.event_camera)
    assert speed.shape == err.t_us.shape and (speed >= 0).all()
    path = plot_tracking_curves(trajs, seq.ground_truth, tmp_path / "p" / "curves.png",
                                title="test", pixel_speed=(err.t_us, speed))
    assert_png(path)
    series = {"shifted": SpeedErrors(speed, err.position_cm, err.rotation_deg)}
    assert_png(plot_error_vs_speed(series, tmp_path / "p" / "speed.png"))
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == ["curves.png", "speed.png"]


def test_pixel_speed_of_a_point_translating_sideways():
    class Uniform:  # the object moves along x at 0.5 m/s at z = 1 m
        def pose_at(self, t_us):
            t = torch.as_tensor(t_us, dtype=torch.float64).reshape(-1) * 1e-6
            T = torch.eye(4, dtype=torch.float64).repeat(len(t), 1, 1)
            T[:, 0, 3] = 0.5 * t
            T[:, 2, 3] = 1.0
            return T

        def twist_at(self, t_us):
            n = torch.as_tensor(t_us).reshape(-1).numel()
            return torch.tensor([[0.5, 0, 0, 0, 0, 0]], dtype=torch.float64).repeat(n, 1)

    cam = PinholeCamera(200.0, 200.0, 50.0, 40.0, 100, 80)
    speed = pixel_speed_at(np.array([0, 1000, 2000]), Uniform(), np.zeros((1, 3)), cam)
    np.testing.assert_allclose(speed, 100.0)  # fx * v / z


def test_cuboid_segments_are_the_box_edges():
    v = np.random.default_rng(1).uniform(-1, 1, (50, 3)) * [0.1, 0.2, 0.05]
    seg = cuboid_segments(v)
    assert seg.shape == (12, 2, 3)
    d = np.abs(seg[:, 1] - seg[:, 0])
    extents = v.max(0) - v.min(0)
    for axis in range(3):  # four edges along each axis, each as long as the box
        along = d[:, axis] > 0
        assert along.sum() == 4
        np.testing.assert_allclose(d[along, axis], extents[axis])
        np.testing.assert_allclose(np.delete(d[along], axis, 1), 0)


def test_wireframe_of_the_box_lies_on_its_edges():
    box = procedural_object("box", 0)
    seg = wireframe_segments(box.vertices, box.faces)
    lo, hi = box.vertices.min(0), box.vertices.max(0)
    on_face = (np.isclose(seg, lo, atol=1e-6) | np.isclose(seg, hi, atol=1e-6)).sum(-1)
    assert len(seg) >= 12 and (on_face >= 2).all()


def test_project_segments_drops_what_is_behind_the_camera():
    cam = PinholeCamera(100.0, 100.0, 32.0, 24.0, 64, 48)
    seg = np.array([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], [[0.0, 0.0, 0.0], [0.0, 0.0, -2.0]]])
    pose = np.eye(4)
    pose[2, 3] = 1.0
    uv = project_segments(seg, pose, cam)
    assert uv.shape == (1, 2, 2)
    np.testing.assert_allclose(uv[0], [[32.0, 24.0], [42.0, 24.0]])


def test_overlay_video_frames_and_drawing(tiny_benchmark, tmp_path):
    import imageio.v3 as iio

    seq = Sequence.load(tiny_benchmark / "box_regular")
    plain = tmp_path / "plain.mp4"
    drawn = tmp_path / "drawn.mp4"
    n = write_overlay_video(seq, {}, plain, ground_truth=False)
    assert n == seq.num_rgb
    write_overlay_video(seq, {"exact": gt_trajectory(seq)}, drawn, ground_truth=False, scale=4)
    a = iio.imread(plain)
    b = iio.imread(drawn)
    assert a.shape == (seq.num_rgb, 360, 480, 3)  # auto scale 5 for 96x72
    assert b.shape == (seq.num_rgb, 288, 384, 3)
    # the wireframe is drawn where the object is: compare with the same frame, plain
    k = seq.num_rgb // 2
    c = iio.imread(drawn, index=k).astype(float)
    p = write_overlay_video(seq, {}, tmp_path / "plain4.mp4", ground_truth=False, scale=4)
    assert p == seq.num_rgb
    ref = iio.imread(tmp_path / "plain4.mp4", index=k).astype(float)
    diff = np.abs(c - ref).sum(-1) > 60
    pose = seq.ground_truth.pose_at(int(seq.rgb_times_us[k])).numpy()
    uv = project_segments(cuboid_segments(procedural_object("box", 0).vertices), pose,
                          seq.meta.event_camera).reshape(-1, 2) * 4
    ys, xs = np.nonzero(diff[40:])  # below the legend
    ys = ys + 40
    assert len(xs) > 50
    inside = ((xs >= uv[:, 0].min() - 8) & (xs <= uv[:, 0].max() + 8)
              & (ys >= uv[:, 1].min() - 8) & (ys <= uv[:, 1].max() + 8))
    assert inside.mean() > 0.9
    limited = write_overlay_video(seq, {}, tmp_path / "short.mp4", max_frames=3)
    assert limited == 3 and iio.imread(tmp_path / "short.mp4").shape[0] == 3
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".")]
