"""Trajectories: seeded, smooth, in view, and twists that match finite differences of poses."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.geometry import twist_between
from evtrack.sim.config import CameraConfig, TrajectoryConfig
from evtrack.sim.trajectory import (
    left_jacobian,
    random_trajectory,
    rotvec_to_matrix,
    static_trajectory,
)

CAM = CameraConfig().camera()
RADIUS = 0.13


def _fd_twist(traj, t: np.ndarray, h: float = 1e-5) -> np.ndarray:
    T0 = torch.from_numpy(traj.pose(t - h))
    T1 = torch.from_numpy(traj.pose(t + h))
    return twist_between(T0, T1, 2 * h).numpy()


@pytest.mark.parametrize("preset", ["regular", "faster"])
def test_twist_matches_finite_differences_of_poses(preset: str) -> None:
    traj = random_trajectory(3.0, CAM, RADIUS, TrajectoryConfig(preset=preset), seed=11)
    t = np.random.default_rng(0).uniform(0.01, 2.99, 300)
    analytic = traj.twist(t)
    fd = _fd_twist(traj, t)
    scale = np.abs(analytic).max(axis=0)
    np.testing.assert_allclose(analytic, fd, atol=1e-5 * scale.max() + 1e-8, rtol=1e-4)
    assert np.abs(analytic[:, 3:]).max() > 0.3  # it does rotate


def test_point_velocity_convention() -> None:
    """Ṗ = v_o + ω × P for an object point, by differencing its camera coordinates."""
    traj = random_trajectory(1.0, CAM, RADIUS, seed=3)
    X = np.array([0.05, -0.02, 0.03])
    for t in (0.1, 0.45, 0.8):
        h = 1e-6
        P = lambda s: traj.pose(s)[:3, :3] @ X + traj.pose(s)[:3, 3]  # noqa: E731
        fd = (P(t + h) - P(t - h)) / (2 * h)
        V = traj.twist(t)
        np.testing.assert_allclose(V[:3] + np.cross(V[3:], P(t)), fd, rtol=1e-5, atol=1e-7)


def test_seeded() -> None:
    a = random_trajectory(2.0, CAM, RADIUS, seed=5)
    b = random_trajectory(2.0, CAM, RADIUS, seed=5)
    c = random_trajectory(2.0, CAM, RADIUS, seed=6)
    t = np.linspace(0, 2, 50)
    np.testing.assert_array_equal(a.pose(t), b.pose(t))
    assert not np.allclose(a.pose(t), c.pose(t))


@pytest.mark.parametrize("seed", range(6))
def test_stays_in_view_and_covers_duration(seed: int) -> None:
    cfg = TrajectoryConfig(preset="faster" if seed % 2 else "regular")
    traj = random_trajectory(2.0, CAM, RADIUS, cfg, seed=seed)
    assert traj.start <= 0.0 and traj.end >= 2.0
    t = np.linspace(0.0, 2.0, 4001)
    p = traj.pose(t)[:, :3, 3]
    assert (p[:, 2] >= 0.4 - 1e-9).all() and (p[:, 2] <= 1.2 + 1e-9).all()
    uv = CAM.project(torch.from_numpy(p)).numpy()
    margin = 0.5 * CAM.fx * RADIUS / p[:, 2]
    assert (uv[:, 0] >= margin - 1e-6).all() and (uv[:, 0] <= CAM.width - 1 - margin + 1e-6).all()
    assert (uv[:, 1] >= margin - 1e-6).all() and (uv[:, 1] <= CAM.height - 1 - margin + 1e-6).all()


def test_smooth_across_knots_and_rest_at_reversals() -> None:
    traj = random_trajectory(4.0, CAM, RADIUS, TrajectoryConfig(reversal_probability=0.5), seed=2)
    inner = traj.knot_times[1:-1]
    inner = inner[(inner > 0.01) & (inner < 3.99)]
    eps = 1e-7
    np.testing.assert_allclose(traj.twist(inner - eps), traj.twist(inner + eps), atol=1e-4)
    rest = traj.knot_times[traj.reversals]
    rest = rest[(rest > 0) & (rest < 4.0)]
    assert len(rest) > 0
    np.testing.assert_allclose(traj.twist(rest), 0.0, atol=1e-9)
    # the speed drops towards a reversal: a speed minimum there
    speed = lambda s: np.linalg.norm(traj.twist(s)[..., :3], axis=-1)  # noqa: E731
    assert (speed(rest) <= speed(rest - 0.02) + 1e-12).all()


def test_faster_preset_is_faster() -> None:
    t = np.linspace(0, 2, 400)
    v = {}
    for preset in ("regular", "faster"):
        speeds = [np.linalg.norm(random_trajectory(2.0, CAM, RADIUS, TrajectoryConfig(
            preset=preset), seed=s).twist(t)[:, 3:], axis=1).mean() for s in range(4)]
        v[preset] = np.mean(speeds)
    assert v["faster"] > 1.5 * v["regular"]


def test_static_trajectory() -> None:
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.1, 0.7]
    traj = static_trajectory(T, 1.0)
    np.testing.assert_array_equal(traj.pose(np.array([0.0, 0.5, 1.0])), np.stack([T] * 3))
    assert np.abs(traj.twist(np.array([0.3, 2.0]))).max() == 0.0


def test_rotation_helpers_match_scipy() -> None:
    from scipy.spatial.transform import Rotation

    r = np.random.default_rng(0).normal(0, 1.2, (20, 3))
    r[0] = 0.0
    r[1] = [1e-9, 0, 0]
    np.testing.assert_allclose(rotvec_to_matrix(r), Rotation.from_rotvec(r).as_matrix(),
                               atol=1e-12)
    # left Jacobian: d/ds exp(r + s·d) exp(r)^T at s=0 equals [J_l d]x (finite differences)
    d = np.random.default_rng(1).normal(size=(20, 3))
    h = 1e-6
    D = (rotvec_to_matrix(r + h * d) - rotvec_to_matrix(r - h * d)) / (2 * h)
    W = D @ rotvec_to_matrix(r).transpose(0, 2, 1)
    w = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], -1)
    np.testing.assert_allclose(w, (left_jacobian(r) @ d[..., None])[..., 0], atol=1e-7)
