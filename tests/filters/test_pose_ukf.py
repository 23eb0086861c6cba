"""PoseUKF and PoseTwistUKF: against filterpy's UKF, the exact motion, long runs, gating and
state handling."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.spatial.transform import Rotation

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.filters import PoseTwistUKF, PoseTwistUKFConfig, PoseUKF, PoseUKFConfig, VelocityKF
from evtrack.filters.lie import quat_exp
from evtrack.geometry import integrate_twist, integrate_twist_tq, matrix_to_tq, tq_to_matrix

F64 = torch.float64
MODES = [pytest.param(False, id="closed_form"), pytest.param(True, id="sigma_points")]


def _unit_q(g: torch.Generator, B: int, scale: float = 3.0) -> torch.Tensor:
    return quat_exp(scale * torch.rand(B, 3, generator=g, dtype=F64) - scale / 2)


def _same_rotation(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.minimum((a - b).abs().amax(-1), (a + b).abs().amax(-1)).max())


# ---------------------------------------------------------------------------- exactness
@pytest.mark.parametrize("velocity_bias", [False, True], ids=["plain", "velocity_bias"])
def test_closed_form_equals_sigma_points(velocity_bias: bool) -> None:
    g = torch.Generator().manual_seed(0)
    B = 8
    t0, q0 = torch.randn(B, 3, generator=g, dtype=F64), _unit_q(g, B)
    cfg = {"velocity_bias": velocity_bias, "init_std_velocity_bias": 0.2}
    fast, slow = PoseUKF(B, PoseUKFConfig(**cfg)), PoseUKF(B, PoseUKFConfig(sigma_points=True,
                                                                             **cfg))
    fast.reset(t=t0, q=q0)
    slow.reset(t=t0, q=q0)
    if velocity_bias:  # a bias (m/s per m/s) moving the points, and learnt by the updates
        bias0 = 0.3 * torch.randn(B, 3, generator=torch.Generator().manual_seed(10), dtype=F64)
        fast.bias, slow.bias = bias0.clone(), bias0.clone()
    for i in range(60):
        twist = torch.randn(B, 6, generator=g, dtype=F64) * 2
        fast.predict(twist, 0.01)
        slow.predict(twist, 0.01)
        if i % 5 == 0:
            t_m = fast.t + 0.02 * torch.randn(B, 3, generator=g, dtype=F64)
            q_m = fast.q + 0.02 * torch.randn(B, 4, generator=g, dtype=F64)
            if i == 30:
                t_m[0] += 5.0  # an outlier, rejected by both
            assert torch.equal(fast.update(t_m, q_m), slow.update(t_m, q_m))
    torch.testing.assert_close(fast.t, slow.t, rtol=0, atol=1e-12)
    assert _same_rotation(fast.q, slow.q) < 1e-12
    torch.testing.assert_close(fast.cov, slow.cov, rtol=0, atol=1e-12 * fast.cov.abs().max())
    assert fast.rejected[0] == 1 == slow.rejected[0]
    if velocity_bias:
        assert fast.cov.shape == (B, 9, 9)
        torch.testing.assert_close(fast.bias, slow.bias, rtol=0, atol=1e-12)
        assert float((fast.bias - bias0).abs().max()) > 1e-3


@pytest.mark.parametrize("sigma_points", MODES)
def test_predict_mean_is_the_exact_constant_twist_motion(sigma_points: bool) -> None:
    g = torch.Generator().manual_seed(1)
    B = 5
    t0, q0 = torch.randn(B, 3, generator=g, dtype=F64), _unit_q(g, B)
    twist = torch.randn(B, 6, generator=g, dtype=F64)
    ukf = PoseUKF(B, PoseUKFConfig(sigma_points=sigma_points))
    ukf.reset(t=t0, q=q0)
    for _ in range(100):
        ukf.predict(twist, 0.01)
    t_ref, q_ref = integrate_twist_tq(t0, q0, twist, 1.0)
    torch.testing.assert_close(ukf.t, t_ref, rtol=0, atol=1e-12)
    assert _same_rotation(ukf.q, q_ref) < 1e-12


# ---------------------------------------------------------------------------- filterpy stand-in
def _filterpy_pose_ukf(cfg: PoseUKFConfig, x0: np.ndarray) -> UnscentedKalmanFilter:
    """filterpy's UKF on the Euclidean stand-in state [t, rotation vector]; the motion is
    computed with evtrack.geometry (kornia) and scipy, independently of evtrack.filters."""

    def fx(x: np.ndarray, dt: float, twist: np.ndarray) -> np.ndarray:
        q = Rotation.from_rotvec(x[3:]).as_quat()[[3, 0, 1, 2]]
        T = tq_to_matrix(torch.as_tensor(x[:3])[None], torch.as_tensor(q)[None])
        t1, q1 = matrix_to_tq(integrate_twist(T, torch.as_tensor(twist)[None], dt))
        rotvec = Rotation.from_quat(q1[0].numpy()[[1, 2, 3, 0]]).as_rotvec()
        return np.concatenate([t1[0].numpy(), rotvec])

    points = MerweScaledSigmaPoints(
        6, alpha=cfg.sigma_alpha, beta=cfg.sigma_beta, kappa=cfg.sigma_kappa
    )
    ukf = UnscentedKalmanFilter(dim_x=6, dim_z=6, dt=0.01, hx=lambda x: x, fx=fx, points=points)
    ukf.x = x0.copy()
    ukf.P = np.diag([cfg.init_std_translation**2] * 3 + [cfg.init_std_rotation**2] * 3)
    return ukf


@pytest.mark.parametrize("sigma_points", MODES)
@pytest.mark.parametrize("rotating", [False, True])
def test_matches_filterpy_ukf_on_euclidean_stand_in(sigma_points: bool, rotating: bool) -> None:
    # Without rotation the stand-in is exact (the tangent at the identity is Euclidean); with
    # small rotations the two differ by second-order (BCH) terms only.
    g = torch.Generator().manual_seed(2)
    cfg = PoseUKFConfig(
        sigma_points=sigma_points,
        init_std_rotation=0.01,
        meas_std_rotation=0.005,
        q_rotation=1e-4,
        gate_chi2=math.inf,
    )
    x0 = np.array([0.1, -0.05, 0.8, 0.0, 0.0, 0.0])
    ref = _filterpy_pose_ukf(cfg, x0)
    ours = PoseUKF(1, cfg)
    ours.reset(t=torch.as_tensor(x0[:3])[None], q=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64))
    R = ours.meas_cov[None].clone()
    Q = np.diag([cfg.q_translation] * 3 + [cfg.q_rotation] * 3)
    for i in range(60):
        twist = 0.2 * torch.randn(1, 6, generator=g, dtype=F64)
        twist[:, 3:] *= 0.05 if rotating else 0.0
        ref.Q = Q * 0.01
        ref.predict(dt=0.01, twist=twist[0].numpy())
        ours.predict(twist, 0.01)
        if i % 6 == 5:
            z = ref.x + np.concatenate(
                [0.005 * np.random.default_rng(i).standard_normal(3), np.zeros(3)]
            )
            if rotating:
                z[3:] += 0.003 * np.random.default_rng(100 + i).standard_normal(3)
            # filterpy reuses the propagated points; we redraw them after adding Q, as in the
            # non-augmented UKF, so redraw filterpy's too.
            ref.sigmas_f = ref.points_fn.sigma_points(ref.x, ref.P)
            ref.update(z, R=R[0].numpy())
            q_m = Rotation.from_rotvec(z[3:]).as_quat()[[3, 0, 1, 2]]
            ours.update(torch.as_tensor(z[:3])[None], torch.as_tensor(q_m)[None], R)
    rotvec = Rotation.from_quat(ours.q[0].numpy()[[1, 2, 3, 0]]).as_rotvec()
    tol_x, tol_p = (1e-6, 1e-3) if rotating else (1e-12, 1e-10)
    np.testing.assert_allclose(ours.t[0].numpy(), ref.x[:3], rtol=0, atol=tol_x)
    np.testing.assert_allclose(rotvec, ref.x[3:], rtol=0, atol=tol_x)
    np.testing.assert_allclose(
        ours.cov[0].numpy(), ref.P, rtol=tol_p, atol=tol_p * np.abs(ref.P).max()
    )


# ---------------------------------------------------------------------------- long runs
@pytest.mark.parametrize("cls", [PoseUKF, PoseTwistUKF])
def test_long_run_keeps_unit_quaternion_and_spd_covariance(cls: type) -> None:
    # 1e5 track-steps: B tracks stepped in lockstep, with varied twists, noise levels (down to
    # near-singular measurements), outliers and gaps.
    g = torch.Generator().manual_seed(3)
    B, steps = (200, 500) if cls is PoseUKF else (100, 1000)
    filt = cls(B)
    filt.reset(t=torch.randn(B, 3, generator=g, dtype=F64), q=_unit_q(g, B))
    meas_scale = torch.logspace(-5, -1, B, dtype=F64)  # m and rad
    R = torch.diag_embed(meas_scale[:, None].expand(B, 6) ** 2)
    twist = (
        torch.randn(B, 6, generator=g, dtype=F64) * torch.linspace(0.1, 20.0, B, dtype=F64)[:, None]
    )
    for i in range(steps):
        if cls is PoseUKF:
            filt.predict(twist, 1e-3)
        else:
            filt.predict(1e-3)
        if i % 10 == 0:
            t_m = filt.t + meas_scale[:, None] * torch.randn(B, 3, generator=g, dtype=F64)
            q_m = filt.q + meas_scale[:, None] * torch.randn(B, 4, generator=g, dtype=F64)
            t_m[i % B] += 10.0  # an outlier
            filt.update(t_m, q_m, R, valid=torch.rand(B, generator=g) < 0.9)
        assert (filt.q.norm(dim=-1) - 1).abs().max() < 1e-12
        assert torch.equal(filt.cov, filt.cov.transpose(-1, -2))
        assert (torch.linalg.cholesky_ex(filt.cov).info == 0).all()
    assert torch.linalg.eigvalsh(filt.cov).min() > 0
    assert torch.isfinite(filt.t).all()
    assert (filt.rejected > 0).any()


def test_ten_seconds_without_measurements() -> None:
    # The velocity filter decays its twist to zero; the pose UKF it drives comes to rest, and
    # nothing becomes NaN; the covariance grows as Q·t.
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    kf = VelocityKF(cam, 2)
    kf.reset(twist=torch.tensor([[0.5, -0.2, 0.1, 2.0, -1.0, 3.0]] * 2, dtype=F64))
    ukf = PoseUKF(2)
    ukf.reset(
        t=torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=F64),
        q=torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64),
    )
    cv = PoseTwistUKF(2, PoseTwistUKFConfig(alpha=0.5))
    cv.reset(t=ukf.t, q=ukf.q, twist=kf.twist)
    cov0 = ukf.cov.clone()
    for i in range(1000):  # 10 ms steps (the decay is per second, whatever the step)
        ukf.predict(kf.predict(1e-2), 1e-2)
        cv.predict(1e-2)
        if i == 499:
            t_half = ukf.t.clone()
    for x in (kf.twist, kf.cov, ukf.t, ukf.q, ukf.cov, cv.t, cv.q, cv.twist, cv.cov):
        assert torch.isfinite(x).all()
    assert kf.twist.abs().max() < 1e-12 and cv.twist.abs().max() < 1e-12
    torch.testing.assert_close(ukf.t, t_half, rtol=0, atol=1e-12)  # at rest
    grown = torch.diagonal(ukf.cov - cov0, dim1=-2, dim2=-1)
    torch.testing.assert_close(grown, (ukf.q_density * 10.0).expand(2, 6))


# ---------------------------------------------------------------------------- gating
def _started(B: int = 3, **cfg: float) -> PoseUKF:
    ukf = PoseUKF(B, PoseUKFConfig(**cfg))
    ukf.reset(
        t=torch.tensor([[0.0, 0.0, 1.0]] * B, dtype=F64),
        q=torch.tensor([[1.0, 0, 0, 0]] * B, dtype=F64),
    )
    return ukf


def test_gating_rejects_outliers_and_reinitialises_after_a_run() -> None:
    ukf = _started(2, reinit_after=3)
    good_t = ukf.t + 0.01
    far_t = ukf.t + torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=F64)
    q = ukf.q.clone()
    used = ukf.update(far_t, q)
    assert used.tolist() == [False, True] and ukf.rejected.tolist() == [1, 0]
    assert ukf.t[0].tolist() == [0.0, 0.0, 1.0]  # untouched by the rejected pose
    ukf.update(far_t, q)
    assert ukf.rejected_run.tolist() == [2, 0]
    used = ukf.update(far_t, q)  # third in a row: re-initialise on it
    assert used.tolist() == [True, True] and ukf.reinitialised.tolist() == [1, 0]
    torch.testing.assert_close(ukf.t[0], far_t[0])
    torch.testing.assert_close(ukf.cov[0], ukf.meas_cov)
    assert ukf.rejected.tolist() == [3, 0] and ukf.rejected_run.tolist() == [0, 0]
    ukf.update(ukf.t + 0.001, q)
    assert ukf.rejected_run.tolist() == [0, 0]
    ukf.update(far_t + 5.0, q)  # both rejected: a new run starts
    assert ukf.rejected_run.tolist() == [1, 1]
    ukf.update(good_t + torch.tensor([1.0, 0.0, 0.0], dtype=F64), q)  # near track 0's new state
    assert ukf.rejected_run.tolist() == [0, 2]


@pytest.mark.parametrize("cls", [PoseUKF, PoseTwistUKF])
@pytest.mark.parametrize("fast_path", [True, False])
def test_reinit_after_of_one_update_overrides_the_config(cls: type, fast_path: bool) -> None:
    """``update(..., reinit_after=1)``: a rejected pose re-initialises at once; accepted poses
    and later updates are unaffected (one CPU track: the fast path, or torch)."""
    ukf = cls(1, fast_path=fast_path)  # the config's reinit_after: 5
    ukf.reset(t=torch.tensor([[0.0, 0.0, 1.0]], dtype=F64),
              q=torch.tensor([[1.0, 0, 0, 0]], dtype=F64))
    far = torch.tensor([[0.5, 0.0, 1.0]], dtype=F64)
    near = torch.tensor([[0.001, 0.0, 1.0]], dtype=F64)
    q = ukf.q.clone()
    assert ukf.update(near, q, reinit_after=1).tolist() == [True]  # accepted: fused
    assert ukf.reinitialised.tolist() == [0] and ukf.rejected.tolist() == [0]
    assert ukf.update(far, q).tolist() == [False]  # the config's reinit_after: rejected
    assert ukf.rejected_run.tolist() == [1]
    assert ukf.update(far, q, reinit_after=1).tolist() == [True]
    assert ukf.rejected.tolist() == [2] and ukf.reinitialised.tolist() == [1]
    assert ukf.rejected_run.tolist() == [0]
    torch.testing.assert_close(ukf.t, far)
    assert ukf.update(far + 0.5, q).tolist() == [False]  # back to the config's rule
    with pytest.raises(ConfigError, match="reinit_after must be >= 1"):
        ukf.update(far, q, reinit_after=0)


def test_gate_threshold_is_the_mahalanobis_distance() -> None:
    ukf = _started(1, gate_chi2=9.0, init_std_translation=0.1)
    R = torch.eye(6, dtype=F64)[None] * 1e-4
    S = ukf.cov[0, 0, 0] + R[0, 0, 0]  # innovation variance along x
    inside = ukf.t + torch.tensor([[2.99, 0.0, 0.0]], dtype=F64) * S.sqrt()
    outside = ukf.t + torch.tensor([[3.01, 0.0, 0.0]], dtype=F64) * S.sqrt()
    probe = _started(1, gate_chi2=9.0, init_std_translation=0.1)
    assert not probe.update(outside, probe.q, R)[0]
    assert ukf.update(inside, ukf.q, R)[0]


def test_first_pose_initialises_and_missing_poses_are_skipped() -> None:
    ukf = PoseUKF(3)
    assert not ukf.initialized.any()
    t_m = torch.tensor([[5.0, 0, 0], [0, 5.0, 0], [0, 0, 5.0]], dtype=F64)
    q_m = -_unit_q(torch.Generator().manual_seed(4), 3)
    t_m[2, 0] = math.nan  # a NaN pose is a missing pose, not a rejected one
    used = ukf.update(t_m, q_m, valid=torch.tensor([True, False, True]))
    assert used.tolist() == [True, False, False]
    assert ukf.initialized.tolist() == [True, False, False]
    torch.testing.assert_close(ukf.t[0], t_m[0])
    assert _same_rotation(ukf.q[:1], q_m[:1]) < 1e-15
    assert ukf.rejected.tolist() == [0, 0, 0]
    assert torch.isfinite(ukf.t).all() and torch.isfinite(ukf.cov).all()


def test_measurement_sign_does_not_matter() -> None:
    a, b = _started(1), _started(1)
    q_m = quat_exp(torch.tensor([[0.01, -0.02, 0.005]], dtype=F64))
    t_m = a.t + 0.01
    a.update(t_m, q_m)
    b.update(t_m, -q_m)
    torch.testing.assert_close(a.t, b.t, rtol=0, atol=1e-15)
    assert _same_rotation(a.q, b.q) < 1e-15


# ---------------------------------------------------------------------------- constant velocity
def test_twist_in_state_is_learnt_from_poses_and_fuses_twists() -> None:
    g = torch.Generator().manual_seed(5)
    B = 4
    twist = torch.randn(B, 6, generator=g, dtype=F64) * torch.tensor(
        [0.3] * 3 + [1.5] * 3, dtype=F64
    )
    t_true, q_true = torch.randn(B, 3, generator=g, dtype=F64), _unit_q(g, B)
    cv = PoseTwistUKF(B, PoseTwistUKFConfig(q_linear=1e-3, q_angular=1e-2))  # a steady motion
    cv.reset(t=t_true, q=q_true)
    for i in range(400):  # 2 s at 5 ms, a pose every 20 ms
        cv.predict(5e-3)
        t_true, q_true = integrate_twist_tq(t_true, q_true, twist, 5e-3)
        if i % 4 == 3:
            noise = torch.randn(B, 6, generator=g, dtype=F64) * 1e-3
            cv.update(t_true + noise[:, :3], q_true + noise[:, 3:].repeat(1, 2)[:, :4] * 0.5)
    err = (cv.twist - twist).abs()
    assert err[:, :3].max() < 0.01 and err[:, 3:].max() < 0.03
    assert cv.rejected.sum() == 0
    cv.update_twist(twist, torch.eye(6, dtype=F64) * 1e-8)
    torch.testing.assert_close(cv.twist, twist, rtol=0, atol=1e-3)


def test_twist_state_predict_with_certain_twist_is_exact() -> None:
    g = torch.Generator().manual_seed(6)
    B = 3
    t0, q0, twist = (
        torch.randn(B, 3, generator=g, dtype=F64),
        _unit_q(g, B),
        torch.randn(B, 6, generator=g, dtype=F64),
    )
    cfg = PoseTwistUKFConfig(
        init_std_linear=1e-9, init_std_angular=1e-9, q_linear=0.0, q_angular=0.0
    )
    cv = PoseTwistUKF(B, cfg)
    cv.reset(t=t0, q=q0, twist=twist)
    for _ in range(50):
        cv.predict(0.02)
    t_ref, q_ref = integrate_twist_tq(t0, q0, twist, 1.0)
    torch.testing.assert_close(cv.t, t_ref, rtol=0, atol=1e-9)
    assert _same_rotation(cv.q, q_ref) < 1e-9


# ---------------------------------------------------------------------------- state handling
@pytest.mark.parametrize("cls", [PoseUKF, PoseTwistUKF])
def test_state_dict_round_trip_reset_and_device(cls: type, device: torch.device) -> None:
    g = torch.Generator().manual_seed(7)
    filt = cls(4)
    filt.reset(t=torch.randn(4, 3, generator=g, dtype=F64), q=_unit_q(g, 4))
    args = (torch.randn(4, 6, generator=g, dtype=F64), 0.01) if cls is PoseUKF else (0.01,)
    filt.predict(*args)
    filt.update(filt.t + 3.0, filt.q)  # rejected: counters move
    other = cls(1)
    other.load_state_dict(filt.state_dict())
    for name, buf in filt.named_buffers():
        assert torch.equal(buf, getattr(other, name)), name
    moved = other.to(device)
    assert moved.t.device.type == device.type
    moved.predict(*[a.to(device) if isinstance(a, torch.Tensor) else a for a in args])
    filt.predict(*args)
    torch.testing.assert_close(moved.t.cpu(), filt.t)
    filt.reset()
    assert not filt.initialized.any() and filt.rejected.sum() == 0
    f32 = cls(2).to(torch.float32)
    f32.update(torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0]] * 2))
    assert f32.t.dtype == torch.float32 and f32.initialized.all()


def test_inputs_are_checked() -> None:
    ukf = PoseUKF(2)
    with pytest.raises(ValueError, match="twist must have shape"):
        ukf.predict(torch.zeros(3, 6), 0.01)
    with pytest.raises(ValueError, match="q_meas must have shape"):
        ukf.update(torch.zeros(2, 3), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="cov_meas must have shape"):
        ukf.update(torch.zeros(2, 3), torch.ones(2, 4), torch.eye(5))
    with pytest.raises(ValueError, match="give both t and q"):
        ukf.reset(t=torch.zeros(2, 3))


# ---------------------------------------------------------------------------- object-centred
def _monte_carlo_position(t0: np.ndarray, std_v: float, std_w: float, duration: float,
                          n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the object's position after ``duration`` s when it moves with an
    unknown constant velocity ``v`` of its origin and turns at ``ω`` about that origin (both
    independent, zero-mean Gaussians), by sampling and exact integration."""
    g = torch.Generator().manual_seed(7)
    v = std_v * torch.randn(n, 3, generator=g, dtype=F64)
    w = std_w * torch.randn(n, 3, generator=g, dtype=F64)
    t = torch.as_tensor(t0, dtype=F64).expand(n, 3)
    twist = torch.cat([v + torch.cross(t, w, dim=-1), w], dim=-1)  # camera-frame [v_o, ω]
    T0 = torch.eye(4, dtype=F64).expand(n, 4, 4).clone()
    T0[:, :3, 3] = t
    p = integrate_twist(T0, twist, duration)[:, :3, 3].numpy()
    return p.mean(0), np.cov(p.T)


@pytest.mark.parametrize("fast_path", [True, False])
def test_unknown_rotation_turns_the_object_about_itself(fast_path: bool) -> None:
    # Starting on a pose with no twist known: the object's predicted position stays put and
    # spreads as v·t, as the Monte-Carlo motion of an object turning about its own origin.
    # Independent spreads of v_o and ω (object_centred=False) swing it about the camera.
    t0 = np.array([0.15, -0.06, 0.5])
    std_v, std_w, steps = 0.5, 3.0, 100
    cfg = dict(q_translation=0.0, q_rotation=0.0, q_linear=0.0, q_angular=0.0,
               init_std_linear=std_v, init_std_angular=std_w)
    mc_mean, mc_cov = _monte_carlo_position(t0, std_v, std_w, steps * 1e-3)
    results = {}
    for centred in (True, False):
        f = PoseTwistUKF(1, PoseTwistUKFConfig(object_centred=centred, **cfg),
                         fast_path=fast_path)
        f.update(torch.tensor(t0[None]), torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
                 cov_meas=torch.eye(6, dtype=F64) * 1e-12)
        for _ in range(steps):
            f.predict(1e-3)
        results[centred] = (f.t[0].numpy(), f.cov[0, :3, :3].numpy())
    mean, cov = results[True]
    assert np.abs(mean - mc_mean).max() < 1e-3  # Monte-Carlo error ~ 0.05 / sqrt(2e4)
    assert np.abs(mean - t0).max() < 1e-3
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(mc_cov)), rtol=0.1)
    # the camera-frame spreads: the mean is pulled towards the camera by centimetres
    mean_cam, _ = results[False]
    assert np.linalg.norm(mean_cam) < np.linalg.norm(t0) - 0.02


def test_object_centred_start_is_the_same_on_both_update_paths() -> None:
    t0 = torch.tensor([[0.3, 0.1, 0.8]], dtype=F64)
    q0 = torch.tensor([[0.9, 0.1, -0.2, 0.3]], dtype=F64)
    fast, slow = PoseTwistUKF(1), PoseTwistUKF(1, fast_path=False)
    for f in (fast, slow):
        f.update(t0, q0)
        f.predict(0.01)
    torch.testing.assert_close(fast.cov, slow.cov, rtol=1e-12, atol=1e-15)
    # the twist block at the start: v_o = v + t x ω, with independent v and ω
    reset = PoseTwistUKF(1)
    reset.reset(t=t0, q=q0)
    cfg = reset.config
    w = torch.randn(3, dtype=F64)
    # Cov(v_o, ω) = [t]x Cov(ω): check it on one direction
    cross = reset.cov[0, 6:9, 9:12] @ w
    expected = torch.cross(t0[0], w, dim=0) * cfg.init_std_angular**2
    torch.testing.assert_close(cross, expected)


def test_object_centred_random_walk() -> None:
    # the twist's random walk is independent in the object's own [v, ω]: after one predict from
    # an exactly known state, Cov(v_o, ω) = dt [t]x q_angular and Var(v_o) grows by |t|² terms
    t0 = torch.tensor([[0.2, -0.1, 0.6]], dtype=F64)
    cfg = PoseTwistUKFConfig(init_std_linear=1e-9, init_std_angular=1e-9)
    f = PoseTwistUKF(1, cfg)
    f.reset(t=t0, q=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
            cov=torch.eye(12, dtype=F64)[None] * 1e-18)
    dt = 1e-3
    f.predict(dt)
    w = torch.tensor([0.3, -1.0, 0.5], dtype=F64)
    torch.testing.assert_close(f.cov[0, 6:9, 9:12] @ w,
                               dt * cfg.q_angular * torch.cross(t0[0], w, dim=0),
                               rtol=1e-6, atol=1e-12)
    camera = PoseTwistUKF(1, PoseTwistUKFConfig(init_std_linear=1e-9, init_std_angular=1e-9,
                                                object_centred=False))
    camera.reset(t=t0, q=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64),
                 cov=torch.eye(12, dtype=F64)[None] * 1e-18)
    camera.predict(dt)
    assert camera.cov[0, 6:9, 9:12].abs().max() < 1e-12


# ---------------------------------------------------------------------------- range updates
def _random_spd(g: torch.Generator, B: int, n: int, scale: float) -> torch.Tensor:
    A = torch.randn(B, n, n, generator=g, dtype=F64) * scale
    return A @ A.transpose(-1, -2) + 1e-4 * torch.eye(n, dtype=F64)


def _assert_state(filt, t0, q0, twist0, P_post, delta, cov_rtol: float) -> None:
    """The filter holds ``(t0, q0, twist0) ⊞ delta`` (the rotation by scipy, independently of
    the filters' quaternion code) and the covariance ``P_post``."""
    torch.testing.assert_close(filt.cov, P_post, rtol=cov_rtol, atol=1e-12)
    torch.testing.assert_close(filt.t, t0 + delta[:, :3], rtol=0, atol=1e-12)
    q_expected = torch.stack([torch.tensor(
        (Rotation.from_rotvec(delta[b, 3:6].numpy()) * Rotation.from_quat(
            q0[b, [1, 2, 3, 0]].numpy())).as_quat()[[3, 0, 1, 2]]) for b in range(len(q0))])
    assert _same_rotation(filt.q, q_expected) < 1e-12
    if twist0 is not None:
        torch.testing.assert_close(filt.twist, twist0 + delta[:, 6:], rtol=0, atol=1e-12)


@pytest.mark.parametrize("cls", [PoseUKF, PoseTwistUKF])
def test_range_update_equals_the_information_form(cls: type) -> None:
    """The range update against the information form of the same linear measurement, an
    independent derivation: ``P⁺ = (P⁻¹ + Hᵀ H / r)⁻¹``, ``δ = P⁺ Hᵀ ν / r`` (tangent at the
    prior mean); the rotation (and a twist in the state) move through the covariance only."""
    g = torch.Generator().manual_seed(3)
    B = 6
    filt = cls(B, fast_path=False)
    n = filt.n
    t0, q0 = torch.randn(B, 3, generator=g, dtype=F64) + torch.tensor([0, 0, 1.0], dtype=F64),\
        _unit_q(g, B)
    P0 = _random_spd(g, B, n, 0.05)
    filt.reset(t=t0, q=q0, cov=P0)
    twist0 = filt.twist.clone() if cls is PoseTwistUKF else None
    u = torch.nn.functional.normalize(torch.randn(B, 3, generator=g, dtype=F64), dim=-1)
    nu = 0.02 * torch.randn(B, generator=g, dtype=F64)
    z = (u * t0).sum(-1) + nu
    r = torch.full((B,), 1e-4, dtype=F64)
    used = filt.update_range(u * 3.0, z, r)  # the direction is normalised
    assert used.all()
    H = torch.zeros(B, 1, n, dtype=F64)
    H[:, 0, :3] = u
    info = torch.linalg.inv(P0) + H.transpose(-1, -2) @ H / r[:, None, None]
    P_post = torch.linalg.inv(info)
    delta = (P_post @ H.transpose(-1, -2)).squeeze(-1) * (nu / r)[:, None]
    _assert_state(filt, t0, q0, twist0, P_post, delta, cov_rtol=1e-8)


def test_range_update_moves_only_along_the_direction_when_uncorrelated() -> None:
    filt = PoseUKF(1)
    t0 = torch.tensor([[0.1, -0.05, 0.8]], dtype=F64)
    filt.reset(t=t0, q=torch.tensor([[1.0, 0, 0, 0]], dtype=F64))
    u = t0 / t0.norm()
    used = filt.update_range(u, (u * t0).sum(-1) + 0.03, 1e-6)
    assert bool(used[0])
    moved = filt.t - t0
    # a diagonal isotropic prior: the correction is along u, nearly the full 3 cm
    assert float(torch.linalg.vector_norm(torch.linalg.cross(moved, u))) < 1e-12
    assert abs(float((moved * u).sum()) - 0.03) < 1e-3
    assert float((filt.q - torch.tensor([[1.0, 0, 0, 0]], dtype=F64)).abs().max()) < 1e-15
    # the variance along u shrinks to about r; across u it is unchanged
    Puu = float(u[0] @ filt.cov[0, :3, :3] @ u[0])
    assert Puu < 1.01e-6
    across = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    across = across - (across @ u[0]) * u[0]
    across = across / across.norm()
    init = filt.config.init_std_translation ** 2
    assert abs(float(across @ filt.cov[0, :3, :3] @ across) - init) < 1e-12


def test_range_gate_and_missing_inputs() -> None:
    """A range beyond the gate is rejected, never re-initialises the filter (even many in a
    row) nor counts as a rejected pose; uninitialised tracks and non-finite inputs are
    skipped."""
    filt = PoseUKF(3)
    filt.reset(t=torch.tensor([[0, 0, 1.0]] * 3, dtype=F64),
               q=torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=F64))
    filt.initialized[2] = False
    u = torch.tensor([[0, 0, 1.0]] * 3, dtype=F64)
    S = filt.config.init_std_translation ** 2 + 1e-4
    limit = math.sqrt(filt.config.range_gate_chi2 * S)
    before = filt.t.clone()
    for _ in range(3 * filt.config.reinit_after):
        used = filt.update_range(u, torch.tensor([1.0 + 1.01 * limit, 1.0, 1.5], dtype=F64),
                                 torch.tensor([1e-4, float("nan"), 1e-4], dtype=F64))
        assert not used.any()
    assert torch.equal(filt.t, before)
    assert filt.rejected.tolist() == [0, 0, 0]
    assert filt.reinitialised.tolist() == [0, 0, 0] and filt.rejected_run.tolist() == [0, 0, 0]
    assert bool(filt.update_range(u, torch.tensor([1.0 + 0.99 * limit, 1.0, 1.0],
                                                   dtype=F64), 1e-4)[0])
    with pytest.raises(ValueError, match="direction"):
        filt.update_range(torch.zeros(2, 3, dtype=F64), torch.ones(3, dtype=F64), 1e-4)


# ---------------------------------------------------------------------------- aligned poses
@pytest.mark.parametrize("cls", [PoseUKF, PoseTwistUKF])
def test_aligned_update_equals_the_information_form(cls: type) -> None:
    """The aligned-pose update against the information form of the same linear measurement
    of the tangent: ``P⁺ = (P⁻¹ + Hᵀ R⁻¹ H)⁻¹``, ``δ = P⁺ Hᵀ R⁻¹ ν`` with ``H = [I₆, 0]`` and
    ``ν = z ⊟ x̄``; a twist in the state moves through the covariance only."""
    g = torch.Generator().manual_seed(5)
    B = 5
    filt = cls(B, fast_path=False)
    n = filt.n
    t0 = torch.randn(B, 3, generator=g, dtype=F64) + torch.tensor([0, 0, 1.0], dtype=F64)
    q0 = _unit_q(g, B)
    P0 = _random_spd(g, B, n, 0.05)
    filt.reset(t=t0, q=q0, cov=P0)
    twist0 = filt.twist.clone() if cls is PoseTwistUKF else None
    R = _random_spd(g, B, 6, 0.02)
    nu = 0.01 * torch.randn(B, 6, generator=g, dtype=F64)
    from evtrack.filters.lie import pose_boxminus, pose_boxplus

    t_m, q_m = pose_boxplus(t0, q0, nu)
    used = filt.update_aligned(t_m, -q_m, R)  # either quaternion sign
    assert used.all()
    torch.testing.assert_close(pose_boxminus(t_m, q_m, t0, q0), nu, rtol=0, atol=1e-12)
    H = torch.zeros(B, 6, n, dtype=F64)
    H[:, :, :6] = torch.eye(6, dtype=F64)
    Rinv = torch.linalg.inv(R)
    P_post = torch.linalg.inv(torch.linalg.inv(P0) + H.transpose(-1, -2) @ Rinv @ H)
    delta = (P_post @ H.transpose(-1, -2) @ Rinv @ nu.unsqueeze(-1)).squeeze(-1)
    _assert_state(filt, t0, q0, twist0, P_post, delta, cov_rtol=1e-7)


def test_aligned_update_leaves_unseen_directions_alone() -> None:
    """A covariance huge about one axis (a can's axis: the depth cannot see that turn) leaves
    the state and its variance about that axis as they were, and corrects the rest."""
    filt = PoseUKF(1)
    t0 = torch.tensor([[0.0, 0.0, 0.8]], dtype=F64)
    q0 = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    filt.reset(t=t0, q=q0)
    P0 = filt.cov.clone()
    from evtrack.filters.lie import pose_boxplus

    t_m, q_m = pose_boxplus(t0, q0, torch.tensor([[0.01, 0, 0, 0, 0.1, 0.1]], dtype=F64))
    R = torch.diag(torch.tensor([1e-6] * 3 + [1e-6, 1e-6, 1e8], dtype=F64))
    assert bool(filt.update_aligned(t_m, q_m, R)[0])
    rotvec = Rotation.from_quat(filt.q[0, [1, 2, 3, 0]].numpy()).as_rotvec()
    assert abs(rotvec[2]) < 1e-6 and abs(rotvec[1] - 0.1) < 1e-3
    assert abs(float(filt.t[0, 0]) - 0.01) < 1e-4
    assert abs(float(filt.cov[0, 5, 5] - P0[0, 5, 5])) < 1e-6 * float(P0[0, 5, 5])
    assert float(filt.cov[0, 4, 4]) < 1.01e-6


def test_aligned_gate_and_missing_inputs() -> None:
    """An aligned pose beyond the gate is rejected and, unlike a detection, never counted nor
    a reason to re-initialise (even many in a row); uninitialised tracks and non-finite
    inputs are skipped."""
    filt = PoseUKF(3)
    t0 = torch.tensor([[0, 0, 1.0]] * 3, dtype=F64)
    q0 = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=F64)
    filt.reset(t=t0, q=q0)
    filt.initialized[2] = False
    R = torch.eye(6, dtype=F64) * 1e-6
    far = t0 + torch.tensor([[0.5, 0, 0], [0.0, 0, 0], [0.0, 0, 0]], dtype=F64)
    q_bad = q0.clone()
    q_bad[1] = float("nan")
    before_t, before_P = filt.t.clone(), filt.cov.clone()
    for _ in range(3 * filt.config.reinit_after):
        assert not filt.update_aligned(far, q_bad, R).any()
    assert torch.equal(filt.t, before_t) and torch.equal(filt.cov, before_P)
    assert filt.rejected.tolist() == [0, 0, 0] and filt.reinitialised.tolist() == [0, 0, 0]
    assert filt.rejected_run.tolist() == [0, 0, 0]
    assert filt.update_aligned(t0 + 0.001, q0, R).tolist() == [True, True, False]
    with pytest.raises(ValueError, match="cov_meas"):
        filt.update_aligned(t0, q0, torch.eye(5, dtype=F64))


@pytest.mark.parametrize("fast_path", [True, False])
def test_bad_steps_and_quaternions_are_errors_or_missing_poses(fast_path: bool) -> None:
    ukf = PoseUKF(1, fast_path=fast_path)
    with pytest.raises(ValueError, match="non-zero quaternion"):
        ukf.reset(t=torch.zeros(1, 3), q=torch.zeros(1, 4))
    with pytest.raises(ValueError, match="finite"):
        ukf.reset(t=torch.full((1, 3), math.nan), q=torch.tensor([[1.0, 0, 0, 0]]))
    ukf.reset(t=torch.tensor([[0.0, 0.0, 1.0]]), q=torch.tensor([[1.0, 0.0, 0.0, 0.0]]))
    for dt in (-0.1, math.nan, math.inf, torch.tensor(-0.1)):
        with pytest.raises(ValueError, match="dt must be"):
            ukf.predict(torch.zeros(1, 6), dt)
    # an all-zero quaternion carries no pose: a missing measurement, the state unchanged
    used = ukf.update(torch.tensor([[0.1, 0.0, 1.0]]), torch.zeros(1, 4))
    assert not bool(used[0])
    torch.testing.assert_close(ukf.t, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))


# ---------------------------------------------------------------------------- velocity bias
def _biased(B: int = 1, **kw) -> PoseUKF:
    return PoseUKF(B, PoseUKFConfig(velocity_bias=True, init_std_velocity_bias=0.2, **kw))


def _se3_motion(twist: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, p) of ``exp(dt [ω×, v_o; 0, 0])``, by scipy's matrix exponential."""
    from scipy.linalg import expm

    v, w = twist[:3], twist[3:]
    X = np.zeros((4, 4))
    X[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    X[:3, 3] = v
    M = expm(dt * X)
    return M[:3, :3], M[:3, 3]


def test_velocity_bias_equals_a_plain_kalman_filter() -> None:
    """The closed form against a plain Kalman filter written out here: state ``[t, θ, b]``,
    ``t' = R t + p + b s dt`` with ``s = |v_o + ω × t|``, ``A = [[R, 0, s dt I], [0, R, 0],
    [0, 0, I]]``, ``H = [I₆, 0]``, rotations by scipy, the motion by a matrix exponential."""
    cfg = PoseUKFConfig(velocity_bias=True, q_velocity_bias=0.02, init_std_velocity_bias=0.1,
                        q_translation=0.01, q_rotation=0.3, gate_chi2=math.inf)
    rng = np.random.default_rng(3)
    t = np.array([0.05, -0.1, 0.9])
    rot = Rotation.from_rotvec([0.3, -0.2, 0.5])
    b = np.zeros(3)
    P = np.diag([cfg.init_std_translation**2] * 3 + [cfg.init_std_rotation**2] * 3
                + [cfg.init_std_velocity_bias**2] * 3)
    Q = np.diag([cfg.q_translation] * 3 + [cfg.q_rotation] * 3 + [cfg.q_velocity_bias] * 3)
    Rm = np.diag([1e-4] * 3 + [4e-4] * 3)
    ours = PoseUKF(1, cfg)
    q0 = rot.as_quat()[[3, 0, 1, 2]]
    ours.reset(t=torch.as_tensor(t)[None], q=torch.as_tensor(q0)[None])
    dt = 2e-3
    for i in range(300):
        twist = rng.normal(size=6) * np.array([0.5, 0.5, 0.5, 2.0, 2.0, 2.0])
        ours.predict(torch.as_tensor(twist)[None], dt)
        Rd, p = _se3_motion(twist, dt)
        db = dt * np.linalg.norm(twist[:3] + np.cross(twist[3:], t))
        t = Rd @ t + p + b * db
        rot = Rotation.from_matrix(Rd) * rot
        A = np.eye(9)
        A[:3, :3] = A[3:6, 3:6] = Rd
        A[:3, 6:] = db * np.eye(3)
        P = A @ P @ A.T + Q * dt
        if i % 25 == 24:  # a pose that keeps pulling the track 2 cm along z: a bias to learn
            t_m = t + np.array([0.0, 0.0, 0.02]) + 0.003 * rng.normal(size=3)
            rot_m = Rotation.from_rotvec(0.01 * rng.normal(size=3)) * rot
            nu = np.concatenate([t_m - t, (rot_m * rot.inv()).as_rotvec()])
            S = P[:6, :6] + Rm
            K = P[:, :6] @ np.linalg.inv(S)
            dx = K @ nu
            t, b = t + dx[:3], b + dx[6:]
            rot = Rotation.from_rotvec(dx[3:6]) * rot
            P = P - K @ S @ K.T
            q_m = rot_m.as_quat()[[3, 0, 1, 2]]
            assert ours.update(torch.as_tensor(t_m)[None], torch.as_tensor(q_m)[None],
                               torch.as_tensor(Rm))[0]
    np.testing.assert_allclose(ours.t[0].numpy(), t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.bias[0].numpy(), b, rtol=0, atol=1e-9)
    ours_rot = Rotation.from_quat(ours.q[0].numpy()[[1, 2, 3, 0]])
    assert (ours_rot * rot.inv()).magnitude() < 1e-9
    np.testing.assert_allclose(ours.cov[0].numpy(), P, rtol=0, atol=1e-9 * np.abs(P).max())
    assert b[2] > 0.05  # learnt: the poses kept saying "further away"


def test_velocity_bias_is_learnt_and_removes_the_drift_between_poses() -> None:
    """A twist that reads the object approaching faster than it does by 15 % of its speed
    (0.4-0.7 m/s), 5 Hz poses with 3 mm / 0.01 rad noise: the bias is learnt (camera frame)
    and the track's position error between the poses falls to half the plain filter's."""
    g = torch.Generator().manual_seed(4)
    true_bias = torch.tensor([0.0, 0.0, -0.15], dtype=F64)
    cfg = dict(q_translation=0.01, q_rotation=0.3)
    plain, biased = PoseUKF(1, PoseUKFConfig(**cfg)), PoseUKF(1, PoseUKFConfig(
        velocity_bias=True, q_velocity_bias=0.01, init_std_velocity_bias=0.05, **cfg))
    t_true = torch.tensor([[0.05, 0.0, 0.8]], dtype=F64)
    q_true = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    for filt in (plain, biased):
        filt.reset(t=t_true, q=q_true)
    dt, steps = 1e-3, 6000
    errors: dict[str, list[float]] = {"plain": [], "biased": []}
    for k in range(steps):
        s = k * dt
        # the object's own motion: its origin sways and it turns; v_o = v - ω × t
        v = 0.4 * torch.tensor([[math.sin(2.1 * s), math.cos(1.7 * s), math.sin(1.3 * s)]],
                               dtype=F64)
        w = torch.tensor([[0.8 * math.cos(1.1 * s), 0.5, -0.6 * math.sin(0.9 * s)]], dtype=F64)
        twist = torch.cat([v - torch.linalg.cross(w, t_true), w], dim=-1)
        t_true, q_true = integrate_twist_tq(t_true, q_true, twist, dt)
        measured = twist.clone()
        measured[:, :3] += true_bias * v.norm()
        for filt in (plain, biased):
            filt.predict(measured, dt)
        if k % 200 == 199:
            t_m = t_true + 0.003 * torch.randn(1, 3, generator=g, dtype=F64)
            q_m = quat_exp(0.01 * torch.randn(1, 3, generator=g, dtype=F64))
            q_m = torch.stack([_quat_mul_np(q_m[0], q_true[0])])
            for filt in (plain, biased):
                filt.update(t_m, q_m)
        if k >= steps // 2:
            for name, filt in (("plain", plain), ("biased", biased)):
                errors[name].append(float((filt.t - t_true).norm()))
    rms = {name: math.sqrt(sum(e * e for e in errs) / len(errs)) for name, errs in errors.items()}
    assert rms["biased"] < 0.6 * rms["plain"], rms
    torch.testing.assert_close(biased.bias[0], -true_bias, rtol=0, atol=0.04)
    assert int(biased.rejected[0]) == 0


@pytest.mark.parametrize("sigma_points", MODES)
def test_velocity_bias_moves_nothing_at_rest(sigma_points: bool) -> None:
    """The bias scales with the object's speed under the twist: a zero twist (an object at
    rest, no events) leaves the pose where it is whatever the bias; a pure rotation about the
    object's own origin moves the origin by nothing either."""
    filt = _biased(1, sigma_points=sigma_points)
    t0 = torch.tensor([[0.1, -0.05, 0.7]], dtype=F64)
    filt.reset(t=t0, q=torch.tensor([[1.0, 0, 0, 0]], dtype=F64))
    filt.bias = torch.tensor([[0.3, -0.2, 0.5]], dtype=F64)
    for _ in range(100):
        filt.predict(torch.zeros(1, 6, dtype=F64), 1e-3)
    torch.testing.assert_close(filt.t, t0, rtol=0, atol=1e-15)
    w = torch.tensor([[0.0, 2.0, 1.0]], dtype=F64)
    about_origin = torch.cat([-torch.linalg.cross(w, t0), w], dim=-1)  # v_o = -ω × t
    filt.predict(about_origin, 1e-3)
    torch.testing.assert_close(filt.t, t0, rtol=0, atol=1e-12)
    filt.predict(torch.tensor([[0.5, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=F64), 0.1)  # 0.5 m/s
    torch.testing.assert_close(filt.t, t0 + torch.tensor([[0.05, 0, 0]], dtype=F64)
                               + 0.05 * filt.bias, rtol=0, atol=1e-12)


def _quat_mul_np(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of two wxyz quaternions (scipy's composition, independent of lie)."""
    ra, rb = (Rotation.from_quat(x.numpy()[[1, 2, 3, 0]]) for x in (a, b))
    xyzw = (ra * rb).as_quat()
    return torch.as_tensor(xyzw[[3, 0, 1, 2]])


def test_velocity_bias_state_handling_and_config() -> None:
    filt = _biased(2)
    assert filt.cov.shape == (2, 9, 9) and torch.equal(filt.bias, torch.zeros(2, 3, dtype=F64))
    filt.reset(t=torch.zeros(2, 3, dtype=F64) + 1, q=torch.tensor([[1.0, 0, 0, 0]] * 2))
    filt.bias = torch.full((2, 3), 0.5, dtype=F64)
    other = _biased(1)
    other.load_state_dict(filt.state_dict())
    assert torch.equal(other.bias, filt.bias) and other.batch_size == 2
    with pytest.raises(RuntimeError, match="bias"):  # a plain filter's state has no bias
        other.load_state_dict(PoseUKF(2).state_dict())
    filt.reset()
    assert torch.equal(filt.bias, torch.zeros(2, 3, dtype=F64))
    torch.testing.assert_close(filt.cov[0, 6:, 6:], 0.04 * torch.eye(3, dtype=F64))
    # a re-initialising pose takes the pose, and keeps the bias and its spread
    filt.reset(t=torch.zeros(2, 3, dtype=F64) + 1, q=torch.tensor([[1.0, 0, 0, 0]] * 2))
    filt.bias = torch.full((2, 3), 0.5, dtype=F64)
    far = torch.full((2, 3), 9.0, dtype=F64)
    for _ in range(filt.config.reinit_after):
        filt.update(far, filt.q)
    assert torch.equal(filt.t, far) and int(filt.reinitialised[0]) == 1
    assert torch.equal(filt.bias, torch.full((2, 3), 0.5, dtype=F64))
    assert float(filt.cov[0, :6, 6:].abs().max()) == 0.0
    with pytest.raises(ConfigError, match="velocity_bias"):
        PoseTwistUKFConfig(velocity_bias=True)
    with pytest.raises(ConfigError, match="q_velocity_bias"):
        PoseUKFConfig(velocity_bias=True, q_velocity_bias=-1.0)
    with pytest.raises(ConfigError, match="init_std_velocity_bias"):
        PoseUKFConfig(init_std_velocity_bias=0.0)
