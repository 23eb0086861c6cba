"""The interaction matrix against finite differences of the projection (not its derivation)."""

from __future__ import annotations

import pytest
import torch

from evtrack.camera import PinholeCamera
from evtrack.filters import interaction_matrix, undistort_flow

# Off-centre principal point and unequal focal lengths, so swapped axes would show.
CAM = PinholeCamera(520.0, 470.0, 301.5, 268.25, 640, 480)
CAM_DIST = PinholeCamera(
    520.0, 470.0, 301.5, 268.25, 640, 480, dist=[-0.21, 0.06, 1e-3, -2e-3, 0.01]
)


def _scene(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Random points in front of the camera (m) and random twists [v (m/s), ω (rad/s)]."""
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor(
        [640.0, 480.0], dtype=torch.float64
    )
    depth = 0.2 + 3.0 * torch.rand(n, generator=g, dtype=torch.float64)
    twist = torch.randn(n, 6, generator=g, dtype=torch.float64) * torch.tensor(
        [0.5] * 3 + [3.0] * 3
    )
    return uv, depth, twist


def _fd_flow(
    cam: PinholeCamera, P: torch.Tensor, twist: torch.Tensor, h: float = 1e-6
) -> torch.Tensor:
    """px/s by central differences of projecting P ± (v + ω × P) h (independent of J)."""
    Pdot = twist[:, :3] + torch.linalg.cross(twist[:, 3:], P, dim=-1)
    return (cam.project(P + h * Pdot) - cam.project(P - h * Pdot)) / (2 * h)


def test_matches_finite_differences() -> None:
    uv, depth, twist = _scene(2000, 0)
    P = CAM.unproject(uv, depth)
    J = interaction_matrix(uv, depth, CAM)
    assert J.shape == (2000, 2, 6) and J.dtype == torch.float64
    pred = (J @ twist.unsqueeze(-1)).squeeze(-1)
    fd = _fd_flow(CAM, P, twist)
    rel = (pred - fd).norm(dim=-1) / fd.norm(dim=-1)
    assert rel.max() < 1e-6


def test_each_twist_component_separately() -> None:
    # A unit twist per axis: catches a sign error confined to one column (the paper's (1+y²)ω_x).
    uv, depth, _ = _scene(300, 1)
    P = CAM.unproject(uv, depth)
    J = interaction_matrix(uv, depth, CAM)
    for k in range(6):
        twist = torch.zeros(300, 6, dtype=torch.float64)
        twist[:, k] = 1.0
        fd = _fd_flow(CAM, P, twist)
        err = (J[..., k] - fd).abs().max() / fd.abs().max()
        assert err < 1e-6, f"column {k}"


def test_distorted_camera_matches_finite_differences() -> None:
    uv_ideal, depth, twist = _scene(1000, 2)
    uv_ideal = (
        0.6 * (uv_ideal - torch.tensor([320.0, 240.0], dtype=torch.float64)) + 320.0
    )  # stay central
    P = CAM_DIST.unproject(CAM_DIST.distort_points(uv_ideal), depth)
    uv = CAM_DIST.project(P)  # measured (distorted) pixels
    J = interaction_matrix(uv, depth, CAM_DIST)
    pred = (J @ twist.unsqueeze(-1)).squeeze(-1)
    fd = _fd_flow(CAM_DIST, P, twist)
    rel = (pred - fd).norm(dim=-1) / fd.norm(dim=-1)
    assert rel.max() < 1e-6


def test_undistort_flow_keeps_each_constraint() -> None:
    # Measured flows in distorted pixels, half reduced to a normal component along a random edge
    # normal; in the ideal image the mapped flows must state the same constraint on J_ideal V.
    g = torch.Generator().manual_seed(3)
    uv_ideal, depth, twist = _scene(400, 3)
    uv_ideal = 0.6 * (uv_ideal - torch.tensor([320.0, 240.0], dtype=torch.float64)) + 320.0
    P = CAM_DIST.unproject(CAM_DIST.distort_points(uv_ideal), depth)
    uv = CAM_DIST.project(P)
    flow_d = _fd_flow(CAM_DIST, P, twist)
    normal = torch.rand(400, generator=g) < 0.5
    n = torch.randn(400, 2, generator=g, dtype=torch.float64)
    n = n / n.norm(dim=-1, keepdim=True)
    measured = torch.where(normal[:, None], (flow_d * n).sum(-1, keepdim=True) * n, flow_d)
    uv_i, flow_i = undistort_flow(CAM_DIST, uv, measured, normal)
    assert torch.allclose(uv_i, uv_ideal, atol=1e-6)
    true_ideal = _fd_flow(CAM, P, twist)  # the pinhole image with the same intrinsics
    full = ~normal
    assert torch.allclose(flow_i[full], true_ideal[full], rtol=1e-6, atol=1e-6)
    m = flow_i[normal].norm(dim=-1)
    proj = (true_ideal[normal] * flow_i[normal]).sum(-1) / m
    assert torch.allclose(proj, m, rtol=1e-6, atol=1e-6)


def test_bad_depth_rows_are_nan_and_others_untouched() -> None:
    uv, depth, _ = _scene(6, 4)
    bad = depth.clone()
    bad[1], bad[2], bad[3], bad[4] = float("nan"), 0.0, -1.0, float("inf")
    J = interaction_matrix(uv, bad, CAM)
    assert torch.isnan(J[1:5]).all()
    good = interaction_matrix(uv, depth, CAM)
    assert torch.equal(J[0], good[0]) and torch.equal(J[5], good[5])


def test_shapes_are_checked() -> None:
    with pytest.raises(ValueError, match="uv must be"):
        interaction_matrix(torch.zeros(4, 3), torch.ones(4), CAM)
    with pytest.raises(ValueError, match="depth"):
        interaction_matrix(torch.zeros(4, 2), torch.ones(5), CAM)


def test_batched_leading_dims_and_float32() -> None:
    uv, depth, _ = _scene(12, 5)
    J = interaction_matrix(uv.reshape(3, 4, 2).float(), depth.reshape(3, 4).float(), CAM)
    assert J.shape == (3, 4, 2, 6) and J.dtype == torch.float32
    ref = interaction_matrix(uv, depth, CAM).reshape(3, 4, 2, 6)
    assert torch.allclose(J.double(), ref, rtol=1e-5)
