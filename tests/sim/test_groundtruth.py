"""Ground-truth flow against finite differences of projected mesh points under the true motion."""

from __future__ import annotations

import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.sim.config import TrajectoryConfig
from evtrack.sim.groundtruth import event_flow, pixel_speeds, plot_speed_cdf, point_flow
from evtrack.sim.objects import make_bottle
from evtrack.sim.trajectory import random_trajectory

# off-centre principal point, unequal focal lengths: swapped axes would show
CAM = PinholeCamera(600.0, 560.0, 330.25, 231.5, 640, 480)


def _projected(traj, X: np.ndarray, t: float) -> np.ndarray:
    T = traj.pose(t)
    P = X @ T[:3, :3].T + T[:3, 3]
    return CAM.project(torch.from_numpy(P)).numpy()


def test_flow_equals_finite_differences_of_projected_mesh_points() -> None:
    mesh = make_bottle(seed=0)
    X = mesh.vertices[::7].astype(np.float64)
    traj = random_trajectory(2.0, CAM, mesh.radius, TrajectoryConfig(preset="faster"), seed=4)
    h = 1e-6
    for t in (0.13, 0.77, 1.52):
        T = traj.pose(t)
        P = X @ T[:3, :3].T + T[:3, 3]
        uv = CAM.project(torch.from_numpy(P)).numpy()
        flow = point_flow(uv, P[:, 2], traj.twist(t), CAM)
        fd = (_projected(traj, X, t + h) - _projected(traj, X, t - h)) / (2 * h)
        assert np.abs(fd).max() > 100.0  # it moves
        np.testing.assert_allclose(flow, fd, rtol=1e-5, atol=1e-3)


def test_event_flow_uses_the_render_that_sees_the_object() -> None:
    traj = random_trajectory(1.0, CAM, 0.1, seed=1)
    h, w = CAM.height, CAM.width
    za = np.full((h, w), 0.8, np.float32)
    zb = np.full((h, w), 0.9, np.float32)
    ma = np.zeros((h, w), bool)
    mb = np.zeros((h, w), bool)
    ma[10, 10] = mb[10, 10] = True   # both: depth interpolated in time
    ma[20, 20] = True                # only a
    mb[30, 30] = True                # only b
    x = np.array([10, 20, 30, 40])
    y = np.array([10, 20, 30, 40])
    t = np.array([1000, 1500, 1800, 1200])
    out = event_flow(x, y, t, 1000, za, ma, 2000, zb, mb, traj, CAM)
    assert out.dtype == np.float32 and np.isnan(out[3]).all()
    depths = [0.8, 0.8, 0.9]  # t=1000 is render a: its depth
    for i in range(3):
        expected = point_flow(np.array([[x[i], y[i]]], float), np.array([depths[i]]),
                              traj.twist(t[i] * 1e-6), CAM)[0]
        np.testing.assert_allclose(out[i], expected, rtol=1e-5)
    mid = event_flow(x[:1], y[:1], np.array([1500]), 1000, za, ma, 2000, zb, mb, traj, CAM)
    np.testing.assert_allclose(mid[0], point_flow(np.array([[10.0, 10.0]]), np.array([0.85]),
                                                  traj.twist(1.5e-3), CAM)[0], rtol=1e-5)


def test_pixel_speeds_and_cdf_plot(tmp_path) -> None:
    traj = random_trajectory(1.0, CAM, 0.1, seed=2)
    X = np.random.default_rng(0).normal(0, 0.03, (50, 3))
    t = np.linspace(0, 1, 40)
    s = pixel_speeds(traj, t, X, CAM)
    h = 1e-6
    fd = np.array([np.linalg.norm((_projected(traj, X, ti + h) - _projected(traj, X, ti - h))
                                  / (2 * h), axis=1).mean() for ti in t])
    np.testing.assert_allclose(s, fd, rtol=1e-5, atol=1e-3)
    plot_speed_cdf({"a": s, "b": 2 * s}, tmp_path / "cdf.png")
    assert (tmp_path / "cdf.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
