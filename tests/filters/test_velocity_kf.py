"""VelocityKF: against filterpy's linear Kalman filter, on simulated rigid motions, and its
state handling."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter

from evtrack.camera import PinholeCamera
from evtrack.filters import VelocityKF, VelocityKFConfig, interaction_matrix, laplacian_weights
from evtrack.geometry import integrate_twist, transform_points

CAM = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480)
PLAIN = VelocityKFConfig(normal_flow=False, weighting=False)


def _rois(g: torch.Generator, B: int, N: int) -> tuple[torch.Tensor, torch.Tensor]:
    uv = torch.rand(B, N, 2, generator=g, dtype=torch.float64) * torch.tensor(
        [640.0, 480.0], dtype=torch.float64
    )
    depth = 0.4 + 0.8 * torch.rand(B, N, generator=g, dtype=torch.float64)
    return uv, depth


def _true_flow(
    cam: PinholeCamera, uv: torch.Tensor, depth: torch.Tensor, twist: torch.Tensor, h: float = 1e-5
) -> torch.Tensor:
    """px/s by central differences of projecting the points moved rigidly for ±h seconds
    (exact constant-twist motion); shares nothing with the interaction matrix."""
    P = cam.unproject(uv, depth)
    eye = torch.eye(4, dtype=torch.float64).expand(twist.shape[0], 4, 4)
    fwd = transform_points(integrate_twist(eye, twist, h), P)
    bwd = transform_points(integrate_twist(eye, twist, -h), P)
    return (cam.project(fwd) - cam.project(bwd)) / (2 * h)


def _random_twists(g: torch.Generator, B: int) -> torch.Tensor:
    def unit(n: int) -> torch.Tensor:
        u = torch.randn(n, 3, generator=g, dtype=torch.float64)
        return u / u.norm(dim=-1, keepdim=True)

    v = unit(B) * (0.2 + 0.8 * torch.rand(B, 1, generator=g, dtype=torch.float64))
    w = unit(B) * (0.5 + 3.5 * torch.rand(B, 1, generator=g, dtype=torch.float64))
    return torch.cat([v, w], dim=-1)


# ---------------------------------------------------------------------------- plain KF
def test_equals_filterpy_kalman_filter_over_1000_steps() -> None:
    g = torch.Generator().manual_seed(0)
    steps, N, cfg = 1000, 8, PLAIN
    kf = VelocityKF(CAM, 1, cfg)
    ref = KalmanFilter(dim_x=6, dim_z=2 * N)
    ref.x = np.zeros(6)
    ref.P = np.diag([cfg.init_std_linear**2] * 3 + [cfg.init_std_angular**2] * 3)
    q = np.diag([cfg.q_linear] * 3 + [cfg.q_angular] * 3)
    # Any flows will do for the equivalence: a rigid motion through J plus noise.
    dts = 0.5e-3 + 1.5e-3 * torch.rand(steps, generator=g, dtype=torch.float64)
    uv, depth = _rois(g, steps, N)
    twist = _random_twists(g, 1)
    H_all = interaction_matrix(uv, depth, CAM)  # (steps, N, 2, 6), filterpy's H
    flow = (H_all @ twist[0, :, None]).squeeze(-1) + 20 * torch.randn(
        steps, N, 2, generator=g, dtype=torch.float64
    )
    mask = torch.ones(steps, N, dtype=torch.bool)
    mask[::7, -1] = False  # padding and a RoI without depth: filterpy sees neither
    depth[::7, 0] = float("nan")
    worst_x = worst_P = 0.0
    for i in range(steps):
        dt = float(dts[i])
        kf(dt, uv[i : i + 1], depth[i : i + 1], flow[i : i + 1], mask=mask[i : i + 1])
        keep = mask[i] & torch.isfinite(depth[i])
        a = cfg.alpha ** (dt / cfg.alpha_dt)
        ref.predict(F=a * np.eye(6), Q=q * dt)
        z = flow[i, keep].reshape(-1).numpy()
        ref.update(z, R=cfg.flow_std**2 * np.eye(len(z)), H=H_all[i, keep].reshape(-1, 6).numpy())
        worst_x = max(worst_x, np.abs(kf.twist[0].numpy() - ref.x).max() / np.abs(ref.x).max())
        worst_P = max(worst_P, np.abs(kf.cov[0].numpy() - ref.P).max() / np.abs(ref.P).max())
    assert worst_x < 1e-9 and worst_P < 1e-9
    assert int(kf.skipped_depth[0]) == len(range(0, steps, 7))


@pytest.mark.parametrize("normal_std", [None, 15.0], ids=["one noise", "normal rows' own"])
def test_weighted_update_is_a_kalman_update_with_inflated_noise(normal_std: float | None) -> None:
    # The information form with weights equals a covariance-form update with R_j = R / ρ_j,
    # R = σ_F² for every row, or σ_N² (normal_flow_std) for a normal-only RoI's one row.
    g = torch.Generator().manual_seed(1)
    cfg = VelocityKFConfig(weighting_reference="predicted", weighting_iterations=1,
                           normal_flow_std=normal_std)
    kf = VelocityKF(CAM, 1, cfg)
    twist0 = _random_twists(g, 1)
    cov0 = torch.diag(torch.tensor([0.3, 0.2, 0.1, 2.0, 1.0, 3.0], dtype=torch.float64))[None]
    uv, depth = _rois(g, 1, 30)
    flow = _true_flow(CAM, uv, depth, 1.3 * twist0)
    flow[0, :5] = 500.0  # outliers
    normal = torch.rand(1, 30, generator=g) < 0.5
    mask = torch.ones(1, 30, dtype=torch.bool)
    V, P, _ = kf.update_state(twist0, cov0, twist0, uv, depth, flow, normal, mask)

    J = interaction_matrix(uv[0], depth[0], CAM).numpy()
    rows, z, var = [], [], []
    for k in range(30):
        F = flow[0, k].numpy()
        n = F / np.linalg.norm(F)
        rows.append(n @ J[k])
        z.append(np.linalg.norm(F))
        var.append((normal_std or cfg.flow_std) ** 2 if normal[0, k] else cfg.flow_std**2)
        if not normal[0, k]:
            rows.append(np.array([-n[1], n[0]]) @ J[k])
            z.append(0.0)
            var.append(cfg.flow_std**2)
    H, z = np.array(rows), np.array(z)
    x0, P0 = twist0[0].numpy(), cov0[0].numpy()
    r = z - H @ x0
    rho = laplacian_weights(
        torch.as_tensor(r)[None],
        torch.ones(1, len(r), dtype=torch.bool),
        None,
        cfg.laplace_scale_min,
        cfg.weight_floor,
    )[0].numpy()
    R = np.diag(np.array(var) / rho)
    S = H @ P0 @ H.T + R
    K = P0 @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(V[0].numpy(), x0 + K @ r, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(P[0].numpy(), (np.eye(6) - K @ H) @ P0, rtol=1e-7, atol=1e-12)


def test_normal_rows_own_noise_equals_repeating_them() -> None:
    """Without weighting, a normal-only row of noise σ_F / 3 carries the information of 9 rows
    of σ_F: ``normal_flow_std`` equals the one-noise filter fed each normal-only RoI 9 times
    (the fast path and the torch path), and ``normal_flow_std = flow_std`` is the default
    filter bit for bit."""
    g = torch.Generator().manual_seed(7)
    base = VelocityKFConfig(weighting=False)
    own = VelocityKFConfig(weighting=False, normal_flow_std=base.flow_std / 3)
    twist = _random_twists(g, 1)
    for fast in (True, False):
        kf, rep = VelocityKF(CAM, 1, own, fast_path=fast), VelocityKF(CAM, 1, base, fast_path=fast)
        plain = VelocityKF(CAM, 1, base, fast_path=fast)
        g2 = torch.Generator().manual_seed(8)
        for _ in range(5):
            uv, depth = _rois(g2, 1, 40)
            flow = _true_flow(CAM, uv, depth, twist) + 20 * torch.randn(
                1, 40, 2, generator=g2, dtype=torch.float64)
            normal = torch.rand(1, 40, generator=g2) < 0.5
            idx = torch.cat([torch.arange(40)] + [torch.nonzero(normal[0])[:, 0]] * 8)
            kf(1e-3, uv, depth, flow, normal)
            rep(1e-3, uv[:, idx], depth[:, idx], flow[:, idx], normal[:, idx])
            plain(1e-3, uv, depth, flow, normal)
            torch.testing.assert_close(kf.twist, rep.twist, rtol=1e-9, atol=1e-9)
            torch.testing.assert_close(kf.cov, rep.cov, rtol=1e-9, atol=1e-12)
        assert (kf.twist - plain.twist).abs().max() > 1e-3  # the option changes the update
    same = VelocityKF(CAM, 1, VelocityKFConfig(normal_flow_std=base.flow_std))
    default = VelocityKF(CAM, 1, VelocityKFConfig())
    for kf in (same, default):
        kf(1e-3, uv, depth, flow, normal)
    assert torch.equal(same.twist, default.twist) and torch.equal(same.cov, default.cov)


# ---------------------------------------------------------------------------- batching, skipping
def test_padded_batch_equals_tracks_run_alone() -> None:
    g = torch.Generator().manual_seed(2)
    sizes = [5, 12, 9]
    B, N = len(sizes), max(sizes)
    twists = _random_twists(g, B)
    batched = VelocityKF(CAM, B)
    # The torch steps on both sides: this pins padding and masks (the single-track fast path
    # is pinned to the torch steps in test_backend_parity.py).
    alone = [VelocityKF(CAM, 1, fast_path=False) for _ in sizes]
    for _ in range(5):
        uv, depth = _rois(g, B, N)
        flow = _true_flow(CAM, uv, depth, twists)
        normal = torch.rand(B, N, generator=g) < 0.5
        mask = torch.arange(N)[None] < torch.tensor(sizes)[:, None]
        flow_pad = torch.where(mask[..., None], flow, torch.nan)  # padding content never matters
        batched(1e-3, uv, depth, flow_pad, normal, mask)
        for b, n in enumerate(sizes):
            alone[b](
                1e-3,
                uv[b : b + 1, :n],
                depth[b : b + 1, :n],
                flow[b : b + 1, :n],
                normal[b : b + 1, :n],
            )
    for b in range(B):
        torch.testing.assert_close(batched.twist[b], alone[b].twist[0], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(batched.cov[b], alone[b].cov[0], rtol=1e-9, atol=1e-14)
    assert batched.skipped_measurements.tolist() == [0, 0, 0]


def test_bad_rois_are_skipped_counted_and_never_propagated() -> None:
    g = torch.Generator().manual_seed(3)
    twist = _random_twists(g, 1)
    uv, depth = _rois(g, 1, 20)
    flow = _true_flow(CAM, uv, depth, twist)
    normal = torch.zeros(1, 20, dtype=torch.bool)
    bad_depth, bad_flow = depth.clone(), flow.clone()
    bad_depth[0, 0], bad_depth[0, 1], bad_depth[0, 2], bad_depth[0, 3] = (
        math.nan,
        0.0,
        -2.0,
        math.inf,
    )
    bad_flow[0, 4] = math.nan
    bad_uv = uv.clone()
    bad_uv[0, 5, 1] = math.inf
    normal_bad = normal.clone()
    normal_bad[0, 6] = True
    bad_flow[0, 6] = 0.0  # a zero normal flow has no direction
    kf = VelocityKF(CAM, 1)
    kf(1e-3, bad_uv, bad_depth, bad_flow, normal_bad)
    assert (kf.skipped_depth.tolist(), kf.skipped_flow.tolist()) == ([4], [3])
    assert torch.isfinite(kf.twist).all() and torch.isfinite(kf.cov).all()
    keep = torch.ones(20, dtype=torch.bool)
    keep[:7] = False
    clean = VelocityKF(CAM, 1)
    clean(1e-3, uv[:, keep], depth[:, keep], flow[:, keep], normal[:, keep])
    torch.testing.assert_close(kf.twist, clean.twist, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(kf.cov, clean.cov, rtol=1e-9, atol=1e-14)


def test_track_without_valid_rois_only_predicts() -> None:
    kf = VelocityKF(CAM, 2)
    kf.reset(twist=torch.ones(2, 6, dtype=torch.float64))
    uv = torch.full((2, 3, 2), 300.0, dtype=torch.float64)
    depth = torch.tensor([[math.nan] * 3, [1.0, 1.0, 1.0]], dtype=torch.float64)
    flow = torch.full((2, 3, 2), 50.0, dtype=torch.float64)
    kf(1e-3, uv, depth, flow)
    predicted = VelocityKF(CAM, 1)
    predicted.reset(twist=torch.ones(1, 6, dtype=torch.float64))
    predicted.predict(1e-3)
    torch.testing.assert_close(kf.twist[0], predicted.twist[0], rtol=1e-14, atol=0)
    torch.testing.assert_close(kf.cov[0], predicted.cov[0], rtol=1e-14, atol=0)
    assert kf.skipped_depth.tolist() == [3, 0]


# ---------------------------------------------------------------------------- the motion model
def test_ten_seconds_of_predicts_decay_to_zero() -> None:
    kf = VelocityKF(CAM, 2)
    kf.reset(twist=torch.tensor([[1.0, -2.0, 0.5, 3.0, 1.0, -4.0]] * 2, dtype=torch.float64))
    for _ in range(10_000):
        kf.predict(1e-3)
    assert torch.isfinite(kf.twist).all() and torch.isfinite(kf.cov).all()
    assert kf.twist.abs().max() < 1e-12
    # The covariance settles at the stationary Q dt / (1 - a²) of the decaying model.
    cfg, a2 = kf.config, kf.config.alpha**2
    stationary = (
        torch.tensor([cfg.q_linear] * 3 + [cfg.q_angular] * 3, dtype=torch.float64)
        * 1e-3
        / (1 - a2)
    )
    torch.testing.assert_close(torch.diagonal(kf.cov, dim1=-2, dim2=-1), stationary.expand(2, 6))
    assert torch.linalg.eigvalsh(kf.cov).min() > 0


def test_decay_per_second_does_not_depend_on_the_step() -> None:
    start = torch.tensor([[0.3, 0.1, -0.2, 1.0, 2.0, -1.0]], dtype=torch.float64)
    fine, coarse = VelocityKF(CAM, 1), VelocityKF(CAM, 1)
    fine.reset(twist=start)
    coarse.reset(twist=start)
    for _ in range(10):
        fine.predict(1e-3)
    coarse.predict(torch.tensor([1e-2], dtype=torch.float64))
    torch.testing.assert_close(fine.twist, coarse.twist, rtol=1e-13, atol=0)
    torch.testing.assert_close(coarse.twist, start * 0.5**10, rtol=1e-13, atol=0)


# ---------------------------------------------------------------------------- the paper's claims
def test_normal_flow_constraint_recovers_twist_from_normal_flows() -> None:
    # Noise-free RoIs that only see their normal flow (aperture problem): with the constraint the
    # twist is recovered; using those flows as full flows (the ablation) is biased.
    g = torch.Generator().manual_seed(4)
    twist = _random_twists(g, 2)
    results = {}
    for on in (True, False):
        kf = VelocityKF(CAM, 2, VelocityKFConfig(normal_flow=on, weighting=False))
        g2 = torch.Generator().manual_seed(5)
        for _ in range(20):
            uv, depth = _rois(g2, 2, 200)
            flow = _true_flow(CAM, uv, depth, twist)
            n = torch.randn(2, 200, 2, generator=g2, dtype=torch.float64)
            n = n / n.norm(dim=-1, keepdim=True)
            flow = (flow * n).sum(-1, keepdim=True) * n
            kf(1e-3, uv, depth, flow, torch.ones(2, 200, dtype=torch.bool))
        results[on] = ((kf.twist - twist).norm(dim=-1) / twist.norm(dim=-1)).max().item()
    assert results[True] < 1e-3
    assert results[False] > 0.2


def _robust_run(
    cfg: VelocityKFConfig, seed: int, steps: int = 40
) -> tuple[float, float, VelocityKF]:
    """Simulated rigid motions: random twists and depths, flows through the projection, 20% of
    RoIs replaced by outliers, half of all RoIs (outliers included) reduced to their normal
    component, a few RoIs without depth, tracks with different RoI counts."""
    g = torch.Generator().manual_seed(seed)
    B, N = 6, 400
    twist = _random_twists(g, B)
    kf = VelocityKF(CAM, B, cfg)
    errs = []
    for _ in range(steps):
        uv, depth = _rois(g, B, N)
        flow = _true_flow(CAM, uv, depth, twist) + 3.0 * torch.randn(
            B, N, 2, generator=g, dtype=torch.float64
        )
        outlier = torch.rand(B, N, generator=g) < 0.2
        angle = 2 * math.pi * torch.rand(B, N, generator=g, dtype=torch.float64)
        magnitude = (
            2
            * flow.norm(dim=-1).amax(-1, keepdim=True)
            * torch.rand(B, N, generator=g, dtype=torch.float64)
        )
        wild = torch.stack([magnitude * torch.cos(angle), magnitude * torch.sin(angle)], dim=-1)
        flow = torch.where(outlier[..., None], wild, flow)
        normal = torch.rand(B, N, generator=g) < 0.5
        edge = torch.randn(B, N, 2, generator=g, dtype=torch.float64)
        edge = edge / edge.norm(dim=-1, keepdim=True)
        flow = torch.where(normal[..., None], (flow * edge).sum(-1, keepdim=True) * edge, flow)
        depth = torch.where(torch.rand(B, N, generator=g) < 0.02, torch.nan, depth)
        mask = torch.arange(N)[None] < torch.randint(200, N + 1, (B, 1), generator=g)
        kf(1e-3, uv, depth, flow, normal, mask)
        lin = ((kf.twist[:, :3] - twist[:, :3]).norm(dim=-1) / twist[:, :3].norm(dim=-1)).max()
        ang = ((kf.twist[:, 3:] - twist[:, 3:]).norm(dim=-1) / twist[:, 3:].norm(dim=-1)).max()
        errs.append((lin.item(), ang.item()))
    tail = errs[-10:]
    return max(e[0] for e in tail), max(e[1] for e in tail), kf


@pytest.mark.parametrize("seed", [0, 1])
def test_recovers_simulated_twists_despite_outliers(seed: int) -> None:
    lin, ang, kf = _robust_run(VelocityKFConfig(), seed)
    assert lin < 0.05 and ang < 0.05
    assert (kf.skipped_depth > 0).all() and (kf.skipped_flow == 0).all()


def test_weighting_is_what_rejects_the_outliers() -> None:
    lin, ang, _ = _robust_run(VelocityKFConfig(weighting=False), 0, steps=15)
    assert max(lin, ang) > 0.2


# ---------------------------------------------------------------------------- distortion
def test_distorted_camera_recovers_twist() -> None:
    cam = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480, dist=[-0.2, 0.05, 1e-3, -1e-3, 0.0])
    g = torch.Generator().manual_seed(6)
    twist = _random_twists(g, 2)
    kf = VelocityKF(cam, 2, VelocityKFConfig(weighting=False))
    pinhole = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    ignored = VelocityKF(pinhole, 2, VelocityKFConfig(weighting=False))
    for _ in range(10):
        uv_ideal, depth = _rois(g, 2, 100)
        uv_ideal = 0.7 * (
            uv_ideal - torch.tensor([330.0, 250.0], dtype=torch.float64)
        ) + torch.tensor([330.0, 250.0], dtype=torch.float64)
        P = cam.unproject(cam.distort_points(uv_ideal), depth)
        uv = cam.project(P)  # what the camera measures
        flow = _true_flow(cam, uv, depth, twist)  # in distorted pixels
        normal = torch.rand(2, 100, generator=g) < 0.5
        edge = torch.randn(2, 100, 2, generator=g, dtype=torch.float64)
        edge = edge / edge.norm(dim=-1, keepdim=True)
        flow = torch.where(normal[..., None], (flow * edge).sum(-1, keepdim=True) * edge, flow)
        kf(1e-3, uv, depth, flow, normal)
        ignored(1e-3, uv, depth, flow, normal)
    # The residual error is the decay's shrinkage; ignoring the distortion costs far more.
    assert ((kf.twist - twist).norm(dim=-1) / twist.norm(dim=-1)).max() < 2e-3
    assert ((ignored.twist - twist).norm(dim=-1) / twist.norm(dim=-1)).max() > 2e-2


# ---------------------------------------------------------------------------- state handling
def _some_steps(kf: VelocityKF, seed: int, steps: int = 3) -> None:
    g = torch.Generator().manual_seed(seed)
    twist = _random_twists(g, kf.batch_size)
    for _ in range(steps):
        uv, depth = _rois(g, kf.batch_size, 30)
        kf(
            1e-3,
            uv.to(kf.twist),
            depth.to(kf.twist),
            _true_flow(CAM, uv, depth, twist).to(kf.twist),
        )


def test_state_dict_round_trip_and_reset() -> None:
    kf = VelocityKF(CAM, 3)
    _some_steps(kf, 7)
    other = VelocityKF(CAM, 1)  # another batch size: load takes the saved one
    other.load_state_dict(kf.state_dict())
    assert other.batch_size == 3
    for name, buf in kf.named_buffers():
        assert torch.equal(buf, getattr(other, name)), name
    _some_steps(kf, 8)
    _some_steps(other, 8)
    assert torch.equal(kf.twist, other.twist) and torch.equal(kf.cov, other.cov)
    kf.reset()
    assert kf.twist.abs().max() == 0 and kf.skipped_measurements.sum() == 0
    torch.testing.assert_close(kf.cov, torch.diag_embed(kf.init_var).expand(3, 6, 6))
    kf.reset(batch_size=5, twist=torch.ones(5, 6))
    assert kf.twist.shape == (5, 6) and kf.twist.dtype == torch.float64


def test_device_and_float32(device: torch.device) -> None:
    kf64 = VelocityKF(CAM, 2)
    kf32 = VelocityKF(CAM, 2).to(device=device, dtype=torch.float32)
    assert kf32.twist.device.type == device.type and kf32.cov.dtype == torch.float32
    _some_steps(kf64, 9)
    _some_steps(kf32, 9)
    torch.testing.assert_close(kf32.twist.cpu().double(), kf64.twist, rtol=1e-2, atol=1e-3)


def test_inputs_are_checked() -> None:
    kf = VelocityKF(CAM, 2)
    uv, depth, flow = torch.zeros(2, 4, 2), torch.ones(2, 4), torch.zeros(2, 4, 2)
    with pytest.raises(ValueError, match="depth must be"):
        kf.update(uv, torch.ones(3, 4), flow)
    with pytest.raises(ValueError, match="flow must be"):
        kf.update(uv, depth, torch.zeros(2, 5, 2))
    with pytest.raises(ValueError, match="mask must be"):
        kf.update(uv, depth, flow, mask=torch.ones(2, 4))
    with pytest.raises(ValueError, match="dt must be"):
        kf.predict(torch.ones(3))


def test_pivot_noise_is_the_object_centred_spread() -> None:
    # process noise independent in the pivot's velocity v and ω, seen as [v_o, ω] with
    # v_o = v - ω × p: its covariance by sampling equals q_matrix after set_pivot
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    kf = VelocityKF(cam)
    diagonal = kf.q_matrix.clone()
    p = torch.tensor([0.1, -0.2, 0.7], dtype=torch.float64)
    kf.set_pivot(p)
    g = torch.Generator().manual_seed(0)
    n = 400_000
    qd = kf.q_density
    v = torch.randn(n, 3, generator=g, dtype=torch.float64) * qd[:3].sqrt()
    w = torch.randn(n, 3, generator=g, dtype=torch.float64) * qd[3:].sqrt()
    X = torch.cat([v - torch.cross(w, p.expand_as(w), dim=-1), w], dim=1)
    sampled = X.T @ X / n
    assert float((sampled - kf.q_matrix).abs().max() / kf.q_matrix.abs().max()) < 0.01
    assert torch.equal(kf.q_matrix, kf.q_matrix.T)
    kf.predict(1e-3)  # the predict adds it
    torch.testing.assert_close(kf.cov[0] - kf.init_var.diag() * 0.25, 1e-3 * kf.q_matrix)
    kf.set_pivot(None)
    assert torch.equal(kf.q_matrix, diagonal)


@pytest.mark.parametrize("fast_path", [True, False])
def test_a_negative_or_non_finite_step_is_an_error(fast_path: bool) -> None:
    kf = VelocityKF(CAM, 1, fast_path=fast_path)
    for dt in (-1.0, math.nan, math.inf, torch.tensor(-1.0), torch.tensor([math.nan])):
        with pytest.raises(ValueError, match="dt must be"):
            kf.predict(dt)
    assert bool(torch.isfinite(kf.twist).all())
    kf.predict(0.0)
    kf.predict(torch.tensor([0.001]))
