"""Geometry helpers against independent computations (scipy, numerical integration)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch
from scipy.spatial.transform import Rotation

from evtrack import geometry as G


def rand_pose(g: torch.Generator, n: int | None = None) -> torch.Tensor:
    shape = () if n is None else (n,)
    q = torch.randn(*shape, 4, generator=g, dtype=torch.float64)
    t = torch.randn(*shape, 3, generator=g, dtype=torch.float64)
    return G.tq_to_matrix(t, q)


def test_skew_is_cross_product():
    g = torch.Generator().manual_seed(0)
    w, p = torch.randn(2, 10, 3, generator=g, dtype=torch.float64)
    assert torch.allclose((G.skew(w) @ p.unsqueeze(-1)).squeeze(-1), torch.cross(w, p, dim=-1))


def test_quaternion_convention_matches_scipy():
    g = torch.Generator().manual_seed(1)
    q = torch.randn(20, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    R = G.tq_to_matrix(torch.zeros(20, 3, dtype=torch.float64), q)[:, :3, :3]
    ref = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()  # scipy is xyzw
    assert np.allclose(R.numpy(), ref, atol=1e-12)


def test_tq_roundtrip_and_sign():
    g = torch.Generator().manual_seed(2)
    T = rand_pose(g, 50)
    t, q = G.matrix_to_tq(T)
    assert bool((q[:, 0] >= 0).all())
    assert torch.allclose(G.tq_to_matrix(t, q), T, atol=1e-10)
    assert torch.allclose(G.tq_to_matrix(t, -q), T, atol=1e-10)


def test_inverse_and_compose():
    g = torch.Generator().manual_seed(3)
    A, B = rand_pose(g, 10), rand_pose(g, 10)
    assert torch.allclose(G.compose(A, G.inverse(A)), torch.eye(4, dtype=torch.float64).expand(
        10, 4, 4), atol=1e-12)
    assert torch.allclose(G.inverse(G.compose(A, B)), G.inverse(B) @ G.inverse(A), atol=1e-12)
    assert torch.allclose(G.inverse(A), torch.linalg.inv(A), atol=1e-12)


def test_transform_points():
    g = torch.Generator().manual_seed(4)
    T = rand_pose(g)
    P = torch.randn(7, 3, generator=g, dtype=torch.float64)
    homog = torch.cat([P, torch.ones(7, 1, dtype=torch.float64)], 1)
    assert torch.allclose(G.transform_points(T, P), (homog @ T.T)[:, :3])


def test_integrate_twist_matches_matrix_exponential():
    g = torch.Generator().manual_seed(5)
    T0 = rand_pose(g, 8)
    V = torch.randn(8, 6, generator=g, dtype=torch.float64)
    dt = 0.37
    T1 = G.integrate_twist(T0, V, dt)
    for i in range(8):
        X = np.zeros((4, 4))
        X[:3, :3] = G.skew(V[i, 3:]).numpy()
        X[:3, 3] = V[i, :3].numpy()
        assert np.allclose(T1[i].numpy(), scipy.linalg.expm(dt * X) @ T0[i].numpy(), atol=1e-12)


def test_integrate_twist_solves_point_ode():
    """RK4 on Ṗ = v + ω × P for object points must land where the integrated pose puts them."""
    g = torch.Generator().manual_seed(6)
    T0 = rand_pose(g)
    V = torch.randn(6, generator=g, dtype=torch.float64)
    P_obj = torch.randn(5, 3, generator=g, dtype=torch.float64)
    P = G.transform_points(T0, P_obj)
    v, w = V[:3], V[3:]

    def f(x):
        return v + torch.cross(w.expand_as(x), x, dim=-1)

    h, steps = 1e-3, 500
    for _ in range(steps):
        k1 = f(P)
        k2 = f(P + 0.5 * h * k1)
        k3 = f(P + 0.5 * h * k2)
        k4 = f(P + h * k3)
        P = P + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    T1 = G.integrate_twist(T0, V, h * steps)
    assert torch.allclose(G.transform_points(T1, P_obj), P, atol=1e-9)


def test_integrate_twist_derivative_convention():
    """ṫ = v + ω × t and Ṙ = [ω]× R at dt → 0 (the package's convention)."""
    g = torch.Generator().manual_seed(7)
    T0 = rand_pose(g)
    V = torch.randn(6, generator=g, dtype=torch.float64)
    h = 1e-6
    dT = (G.integrate_twist(T0, V, h) - G.integrate_twist(T0, V, -h)) / (2 * h)
    t, R = T0[:3, 3], T0[:3, :3]
    assert torch.allclose(dT[:3, 3], V[:3] + torch.cross(V[3:], t, dim=0), atol=1e-7)
    assert torch.allclose(dT[:3, :3], G.skew(V[3:]) @ R, atol=1e-7)


@pytest.mark.parametrize("dt", [0.01, 0.5])
def test_twist_between_inverts_integration(dt):
    g = torch.Generator().manual_seed(8)
    T0 = rand_pose(g, 6)
    V = torch.randn(6, 6, generator=g, dtype=torch.float64) * 0.5
    T1 = G.integrate_twist(T0, V, dt)
    assert torch.allclose(G.twist_between(T0, T1, dt), V, atol=1e-8)


def test_integrate_twist_tq_batched_dt():
    g = torch.Generator().manual_seed(9)
    T0 = rand_pose(g, 4)
    t, q = G.matrix_to_tq(T0)
    V = torch.randn(4, 6, generator=g, dtype=torch.float64)
    dt = torch.tensor([0.0, 0.1, 0.2, 0.3], dtype=torch.float64)
    t1, q1 = G.integrate_twist_tq(t, q, V, dt)
    assert torch.allclose(t1[0], t[0]) and torch.allclose(q1.norm(dim=-1),
                                                       torch.ones(4, dtype=torch.float64))
    for i in range(4):
        ti, _ = G.matrix_to_tq(G.integrate_twist(T0[i], V[i], float(dt[i])))
        assert torch.allclose(t1[i], ti, atol=1e-12)
