"""Quaternion and SE(3) kernels against kornia, scipy and the geometry helpers."""

from __future__ import annotations

import math

import torch
from kornia.geometry.liegroup import So3
from kornia.geometry.quaternion import Quaternion
from scipy.spatial.transform import Rotation

from evtrack.filters.lie import (
    atan2_precise,
    pose_boxminus,
    pose_boxplus,
    quat_conj,
    quat_exp,
    quat_log,
    quat_mul,
    quat_rotate,
    se3_exp,
)
from evtrack.geometry import integrate_twist_tq

G = torch.Generator().manual_seed(0)


def _rotvecs(n: int, max_angle: float = 3.0) -> torch.Tensor:
    axis = torch.randn(n, 3, generator=G, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return axis * max_angle * torch.rand(n, 1, generator=G, dtype=torch.float64)


def _same_rotation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Largest distance between quaternions up to sign."""
    return torch.minimum((a - b).abs().amax(-1), (a + b).abs().amax(-1)).max()


def test_exp_matches_kornia_and_scipy() -> None:
    phi = torch.cat([_rotvecs(200), torch.zeros(1, 3, dtype=torch.float64), 1e-12 * _rotvecs(5)])
    q = quat_exp(phi)
    assert torch.allclose(q, So3.exp(phi).q.data, atol=1e-15)
    xyzw = Rotation.from_rotvec(phi.numpy()).as_quat()
    ref = torch.as_tensor(xyzw)[:, [3, 0, 1, 2]]
    assert _same_rotation(q, ref) < 1e-15


def test_log_inverts_exp_and_ignores_sign() -> None:
    phi = torch.cat(
        [_rotvecs(300, 3.1), torch.zeros(1, 3, dtype=torch.float64), 1e-10 * _rotvecs(5)]
    )
    q = quat_exp(phi)
    assert torch.allclose(quat_log(q), phi, atol=1e-14)
    assert torch.allclose(quat_log(-q), phi, atol=1e-14)  # the double cover


def test_atan2_precise_is_float64_accurate() -> None:
    y = torch.rand(1000, generator=G, dtype=torch.float64)
    x = torch.rand(1000, generator=G, dtype=torch.float64)
    assert torch.allclose(atan2_precise(y, x), torch.atan2(y, x), rtol=0, atol=4e-16)


def test_mul_conj_rotate_against_kornia() -> None:
    a, b = quat_exp(_rotvecs(100)), quat_exp(_rotvecs(100))
    assert torch.allclose(quat_mul(a, b), (Quaternion(a) * Quaternion(b)).data, atol=1e-15)
    assert torch.allclose(
        quat_mul(a, quat_conj(a)),
        torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(100, 4),
        atol=1e-15,
    )
    p = torch.randn(100, 3, generator=G, dtype=torch.float64)
    R = So3(Quaternion(a)).matrix()
    assert torch.allclose(quat_rotate(a, p), (R @ p.unsqueeze(-1)).squeeze(-1), atol=1e-14)


def test_se3_exp_matches_geometry_integrate_twist() -> None:
    # geometry.integrate_twist is kornia's Se3.exp; zero, tiny, series-switch and large angles.
    n = 64
    v = torch.randn(n, 3, generator=G, dtype=torch.float64)
    scales = torch.tensor([0.0, 1e-9, 1e-4, 0.099, 0.1, 0.101, 0.5, 2.5], dtype=torch.float64)
    w = _rotvecs(n, 1.0)
    w = w / w.norm(dim=-1, keepdim=True) * scales.repeat(n // len(scales)).unsqueeze(-1)
    twist = torch.cat([v, w], dim=-1)
    t0 = torch.randn(n, 3, generator=G, dtype=torch.float64)
    q0 = quat_exp(_rotvecs(n))
    qd, pd = se3_exp(twist)  # dt = 1
    t1 = quat_rotate(qd, t0) + pd
    q1 = quat_mul(qd, q0)
    t_ref, q_ref = integrate_twist_tq(t0, q0, twist, 1.0)
    assert torch.allclose(t1, t_ref, atol=1e-13)
    assert _same_rotation(q1, q_ref) < 1e-13


def test_se3_exp_solves_the_point_ode() -> None:
    # RK4 on Ṗ = v + ω × P with small steps: independent of any Lie-group formula.
    twist = torch.tensor([[0.3, -0.2, 0.1, 0.7, -1.1, 0.4]], dtype=torch.float64)
    P = torch.tensor([[0.2, -0.1, 1.5]], dtype=torch.float64)

    def f(p: torch.Tensor) -> torch.Tensor:
        return twist[:, :3] + torch.linalg.cross(twist[:, 3:], p, dim=-1)

    steps, T = 2000, 1.3
    h, p = T / steps, P.clone()
    for _ in range(steps):
        k1 = f(p)
        k2 = f(p + h / 2 * k1)
        k3 = f(p + h / 2 * k2)
        k4 = f(p + h * k3)
        p = p + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    qd, pd = se3_exp(twist * T)
    assert torch.allclose(quat_rotate(qd, P) + pd, p, atol=1e-12)


def test_boxplus_boxminus_round_trip() -> None:
    t = torch.randn(50, 3, generator=G, dtype=torch.float64)
    q = quat_exp(_rotvecs(50))
    delta = torch.cat(
        [torch.randn(50, 3, generator=G, dtype=torch.float64), _rotvecs(50, 3.0)], dim=-1
    )
    t1, q1 = pose_boxplus(t, q, delta)
    assert torch.allclose(pose_boxminus(t1, q1, t, q), delta, atol=1e-13)
    assert torch.allclose(pose_boxminus(t1, -q1, t, q), delta, atol=1e-13)
    assert math.isclose(float(q1.norm(dim=-1).max()), 1.0, abs_tol=1e-15)
