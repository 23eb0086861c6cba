"""The NumPy backend: one track's float64 steps in NumPy and Python floats.

A tracker steps its filters once per ~1 ms velocity step with one track (B = 1). The torch
steps then cost the dispatch of ~150 tiny ops (a few µs each) rather than arithmetic. This
backend (:class:`NumpyBackend`, registered as ``"numpy"`` in :mod:`backends`) runs the same
model written for one track: quaternion and SE(3) algebra on Python floats (:mod:`scalar_lie`),
per-RoI work on the usable RoIs only (gathered once, so no masks) as rows of (k, N) arrays, 6x6
algebra through LAPACK (SciPy's ``posv``). The compiled backend (:mod:`fast_compiled`, numba)
replaces its velocity update and pose predict and adds runs of many steps per call. Results
equal the torch steps to rounding (``tests/filters/test_backend_parity.py``: 1e-12, in the
covariance's metric for the velocity filter; a steep fixed Laplacian scale makes the weights
amplify rounding, as much in the torch steps themselves). A 6x6 that is not positive definite
raises ``numpy.linalg.LinAlgError``, on which the filters rerun the step in torch.

The formulas are those of :mod:`velocity_kf`, :mod:`velocity_model`, :mod:`pose_motion`,
:mod:`pose_measurements`, :mod:`lie` and :mod:`weighting`; see there for the derivations and
units. Shapes drop the batch dimension: a twist is (6,), a covariance (n, n), RoI inputs
(N, 2) and (N,).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dposv as _posv

from evtrack.filters.backend_base import FilterBackend, PoseUpdate, RoiRows, VelocityModel
from evtrack.filters.scalar_lie import (
    Quat,
    Vec3,
    cross,
    normalized,
    quat_exp,
    quat_log,
    quat_mul,
    quat_rotate,
    rotation_matrix,
    se3_exp,
)

__all__ = [
    "NumpyBackend",
    "PoseUpdate",
    "pivot_noise",
    "pose_predict",
    "pose_update",
    "velocity_predict",
    "velocity_update",
]


_EYE6 = np.eye(6)
_ACROSS = np.array([-1.0, 1.0])  # n⊥ = (-ny, nx) scales (ny, nx) by these
_TINY = float(np.finfo(np.float64).tiny)


# ---------------------------------------------------------------------------- VelocityKF
def velocity_predict(
    twist: np.ndarray, cov: np.ndarray, dt: float, log_rate: float, q_matrix: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``V' = a V``, ``P' = a² P + Q dt`` with ``a = exp(dt · ln(alpha)/alpha_dt)``.

    Args:
        twist: (6,). cov: (6,6). dt: seconds. log_rate: ``ln(alpha)/alpha_dt`` (1/s).
        q_matrix: (6,6) process-noise density.
    """
    decay = math.exp(dt * log_rate)
    return twist * decay, cov * (decay * decay) + dt * q_matrix


def pivot_noise(q_density: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """``A diag(q) Aᵀ`` with ``A = [[I, [p]×], [0, I]]`` (:func:`~evtrack.filters.lie.pivot_map`)
    in closed form: ``[[Qv + C Qw Cᵀ, C Qw], [Qw Cᵀ, Qw]]`` with ``C = [p]×``, exactly
    symmetric.

    Args:
        q_density: (6,) diagonal ``[qv, qw]``. pivot: (3,) metres.

    Returns:
        (6, 6) float64.
    """
    px, py, pz = (float(v) for v in pivot)
    skew = np.array([[0.0, -pz, py], [pz, 0.0, -px], [-py, px, 0.0]])
    scaled = skew * q_density[3:]  # C Qw (columns scaled)
    out = np.empty((6, 6))
    out[:3, :3] = scaled @ skew.T
    out[:3, :3] = 0.5 * (out[:3, :3] + out[:3, :3].T)
    out[:3, :3] += np.diag(q_density[:3])
    out[:3, 3:] = scaled
    out[3:, :3] = scaled.T
    out[3:, 3:] = np.diag(q_density[3:])
    return out


def velocity_update(
    model: VelocityModel,
    twist: np.ndarray,
    cov: np.ndarray,
    reference: np.ndarray,
    rois: RoiRows,
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """One track's weighted information-form update from RoI flows (see :mod:`velocity_kf`);
    arguments and results as :meth:`FilterBackend.velocity_update`.

    Raises:
        numpy.linalg.LinAlgError: if a 6x6 information matrix is not positive definite.
    """
    cfg, consts, focal, principal = model
    uv, depth, flow, normal_only, mask = rois
    _, flow_info, scale, scale_min, floor, normal_info = consts
    N = depth.shape[0]
    normal = np.full(N, cfg.assume_normal) if normal_only is None else normal_only
    uv_flat, flow_flat = uv.reshape(-1), flow.reshape(-1)
    if (
        mask is None
        and depth.min() > 0  # False for NaN too
        and math.isfinite(depth.sum())  # False for inf (or a sum over 1e308)
        and math.isfinite(uv_flat @ uv_flat + flow_flat @ flow_flat)  # likewise
    ):  # every RoI usable (the common case)
        n_mask = n_depth = N
    else:
        depth_ok = (depth > 0) & (depth < math.inf)  # False for NaN too
        if mask is not None:
            depth_ok &= mask
        n_mask = N if mask is None else int(np.count_nonzero(mask))
        n_depth = int(np.count_nonzero(depth_ok))
        usable = depth_ok & np.isfinite(uv).all(1) & np.isfinite(flow).all(1)
        uv, depth, flow, normal = uv[usable], depth[usable], flow[usable], normal[usable]
    # Per-RoI values as rows of one (6, N) array (NumPy broadcasts a trailing axis of 2
    # slowly): roi = [x, y, 1/Z, nx, ny, |F|] with n = F/|F| (the image axes for a zero flow).
    roi = np.empty((6, depth.shape[0]))
    f2 = flow * flow
    mag = np.sqrt(f2[:, 0] + f2[:, 1], out=roi[5])
    moving = mag > 0
    all_moving = bool(moving.all())
    if cfg.normal_flow and not all_moving:  # a zero normal flow has no direction
        keep = moving | ~normal
        uv, depth, flow, normal, moving = (a[keep] for a in (uv, depth, flow, normal, moving))
        roi = roi[:, keep]
        mag = roi[5]
    n_valid = depth.shape[0]
    np.subtract(uv.T, principal[:, None], out=roi[:2])
    np.divide(roi[:2], focal[:, None], out=roi[:2])
    np.divide(1.0, depth, out=roi[2])
    if all_moving:
        np.multiply(flow.T, 1.0 / mag, out=roi[3:5])
    else:
        np.multiply(flow.T, 1.0 / np.where(moving, mag, 1.0), out=roi[3:5])
        roi[3, ~moving] = 1.0

    # Rows (see velocity_model.measurement_rows): along n for every RoI, then across n⊥ for the
    # full flows (every RoI without the normal-flow constraint); a row with unit direction e
    # has a = e_u fx, b = e_v fy, its RoI's x, y, 1/Z, and the value z = |F| along, 0 across.
    full = np.flatnonzero(~normal) if cfg.normal_flow else None
    if full is not None and full.shape[0] == 0:  # along rows only
        ab, xyz, z = roi[3:5] * focal[:, None], roi[:3], mag
    else:
        across = roi if full is None else roi.take(full, axis=1)
        ab = np.empty((2, n_valid + across.shape[1]))
        # along: a = nx fx, b = ny fy; across: a = -ny fx, b = nx fy
        np.multiply(roi[3:5], focal[:, None], out=ab[:, :n_valid])
        np.multiply(across[4:2:-1], (focal * _ACROSS)[:, None], out=ab[:, n_valid:])
        xyz = np.concatenate((roi[:3], across[:3]), axis=1)
        z = np.zeros(ab.shape[1])
        z[:n_valid] = mag
    xy, iz = xyz[:2], xyz[2]
    # Hᵀ = [a/Z, b/Z, −p/Z, −(b + y p), a + x p, b x − a y] with p = a x + b y, (6, M)
    HT = np.empty((6, z.shape[0]))
    np.multiply(ab, iz, out=HT[:2])
    t = ab * xy  # [a x, b y]
    p = t[0] + t[1]
    np.multiply(p, iz, out=HT[2])
    np.negative(HT[2], out=HT[2])
    np.multiply(xy, p, out=HT[4:2:-1])  # [x p, y p] into rows 4, 3
    HT[4:2:-1] += ab
    np.negative(HT[3], out=HT[3])
    np.multiply(ab, xy[::-1], out=t)  # [a y, b x]
    np.subtract(t[1], t[0], out=HT[5])

    # Λ = P⁻¹ + Hᵀ W H;  P⁺ = Λ⁻¹;  V⁺ = V + P⁺ Hᵀ W (z − H V)
    prior_info = spd_solve(cov, _EYE6)  # posv reads Λ's lower triangle only
    if cfg.weighting and cfg.weighting_reference == "previous":
        innovation, residual = z - twist @ HT, z - reference @ HT
    else:
        innovation = residual = z - twist @ HT
    passes = cfg.weighting_iterations if cfg.weighting else 1
    rho: np.ndarray | None = None
    post_twist, post_cov = twist, cov
    if cfg.normal_flow and cfg.normal_flow_std is not None:
        # the along rows (the first n_valid) of normal-only RoIs have their own noise
        row_info = np.full(z.shape[0], flow_info)
        row_info[:n_valid][normal] = normal_info
        HTf = HT * row_info  # Hᵀ R⁻¹
    else:
        HTf = HT * flow_info  # Hᵀ R_F⁻¹
    for i in range(passes):
        if cfg.weighting:
            rho = laplacian_weights(
                residual, None if cfg.laplace_scale is None else scale, scale_min, floor, rho
            )
            HTw = HTf * rho  # Hᵀ W, (6, M)
        else:
            HTw = HTf
        info = HTw @ HT.T
        info += prior_info
        if i + 1 < passes:  # only the twist: the next pass's residuals
            post_twist = twist + spd_solve(info, HTw @ innovation)
            residual = z - post_twist @ HT
        else:
            post_cov = spd_inverse(info)
            post_twist = twist + post_cov @ (HTw @ innovation)
    return post_twist, post_cov, n_mask - n_depth, n_depth - n_valid


def laplacian_weights(
    residuals: np.ndarray,
    scale: float | None,
    scale_min: float,
    floor: float,
    previous: np.ndarray | None,
) -> np.ndarray:
    """:func:`weighting.laplacian_weights` for the valid rows (M,) of one track."""
    M = residuals.shape[0]
    if M == 0:
        return residuals.copy()
    k = (M - 1) // 2
    dev = residuals - np.partition(residuals, k)[k]  # minus the lower median
    np.abs(dev, out=dev)
    if scale is None:
        if previous is None:
            b = float(dev.sum()) / M
        else:
            b = float(previous @ dev) / max(float(previous.sum()), _TINY)
        b = max(b, scale_min)
    else:
        b = scale
    # ρ = max(e, min(2b·floor, 1)) with e = exp(-|r - M|/b)
    np.divide(dev, -b, out=dev)
    np.exp(dev, out=dev)
    return np.maximum(dev, min(2.0 * b * floor, 1.0), out=dev)


def spd_solve(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A⁻¹ B`` for a symmetric positive-definite ``A`` (n,n) and ``B`` (n,) or (n,k).

    Raises:
        numpy.linalg.LinAlgError: if ``A`` is not positive definite (the callers then run the
            torch path, which returns NaN instead of raising).
    """
    _, X, info = _posv(A, B, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"LAPACK posv: info {info}")
    return X


def spd_inverse(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive-definite matrix (Cholesky solve against the identity),
    made exactly symmetric.

    (Not LAPACK ``potri``: OpenBLAS runs it on a thread pool, ~10x slower at 6x6.)

    Raises:
        numpy.linalg.LinAlgError: if ``A`` is not positive definite (see :func:`spd_solve`).
    """
    X = spd_solve(A, _EYE6 if A.shape[0] == 6 else np.eye(A.shape[0]))
    return 0.5 * (X + X.T)


# ---------------------------------------------------------------------------- PoseUKF
def pose_predict(
    t: np.ndarray, q: np.ndarray, cov: np.ndarray, twist: np.ndarray, dt: float,
    q_matrix: np.ndarray, bias: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closed-form unscented predict of :meth:`PoseUKF.predict_state` (arguments and
    results as :meth:`FilterBackend.pose_predict`), on Python floats and NumPy.

    ``t' = R_Δ t + p_Δ``, ``q' = q_Δ ⊗ q`` (normalised), ``P' = A P Aᵀ + Q dt`` with
    ``A = diag(R_Δ, R_Δ)``, made exactly symmetric before ``Q dt`` is added. With a velocity
    ``bias`` (m/s per m/s of the object's speed; ``cov`` 9x9): ``t' = R_Δ t + p_Δ + b s dt``
    with ``s = |v_o + ω × t|`` (the prior ``t``), and
    ``A = [[R_Δ, 0, s dt I], [0, R_Δ, 0], [0, 0, I]]``.
    """
    t_new, q_new, cov_new = _pose_predict(
        tuple(t[0].tolist()), tuple(q[0].tolist()), cov[0], twist[0].tolist(), dt, q_matrix,
        None if bias is None else bias[0].tolist(),
    )
    return np.array([t_new]), np.array([q_new]), cov_new[None]


def _pose_predict(
    t: Vec3, q: Quat, cov: np.ndarray, twist: list[float], dt: float, q_matrix: np.ndarray,
    bias: list[float] | None,
) -> tuple[Vec3, Quat, np.ndarray]:
    """:func:`pose_predict` on one track's floats: ``t`` (m), ``q`` (wxyz), ``cov`` (n, n),
    ``twist`` 6 floats, ``bias`` 3 floats or ``None``."""
    rho = (twist[0] * dt, twist[1] * dt, twist[2] * dt)
    phi = (twist[3] * dt, twist[4] * dt, twist[5] * dt)
    qd, pd = se3_exp(rho, phi)
    r = quat_rotate(qd, t)
    t_new = (r[0] + pd[0], r[1] + pd[1], r[2] + pd[2])
    q = normalized(quat_mul(qd, q))
    R = np.array(rotation_matrix(qd))
    n = cov.shape[0]
    A = np.eye(n)
    A[:3, :3] = R
    A[3:6, 3:6] = R
    if bias is not None:
        c = cross((twist[3], twist[4], twist[5]), t)
        db = dt * math.sqrt(sum((twist[i] + c[i]) ** 2 for i in range(3)))
        t_new = (t_new[0] + bias[0] * db, t_new[1] + bias[1] * db, t_new[2] + bias[2] * db)
        A[:3, 6:] = db * np.eye(3)
    t = t_new
    rotated = A @ cov @ A.T
    return t, q, 0.5 * (rotated + rotated.T) + dt * q_matrix


def pose_update(
    t: Vec3,
    q: Quat,
    extra: np.ndarray,
    cov: np.ndarray,
    initialized: bool,
    rejected_run: int,
    t_meas: Vec3,
    q_meas: Quat,
    R: np.ndarray,
    valid: bool,
    gate: float,
    reinit_after: int,
) -> PoseUpdate:
    """The gated closed-form pose update of :meth:`PoseUKF.update_pose_state` (arguments as
    :meth:`FilterBackend.pose_update`).

    ``h(x) = pose``: ``S = P_pp + R``, ``Pxz = P[:, :6]``, ``ν = (t_m, q_m) ⊟ (t, q)``;
    accepted when the track is fresh (``take`` the pose) or ``νᵀ S⁻¹ ν <= gate`` (fuse);
    after ``reinit_after`` rejections in a row the next rejected pose is taken.

    Raises:
        numpy.linalg.LinAlgError: if ``S`` is not positive definite (the callers fall back to
            torch).
    """
    finite = math.isfinite(sum(t_meas) + sum(q_meas)) and bool(np.isfinite(R).all())
    if not (valid and finite):  # a missing pose: the state stays (q renormalised)
        return PoseUpdate(
            t, normalized(q), extra.copy(), cov.copy(), initialized, rejected_run, False, 0, 0
        )
    q_meas = normalized(q_meas)
    if not initialized:
        accept, d2 = True, 0.0
    else:
        n = cov.shape[0]
        Pxz = cov[:, :6]
        S = cov[:6, :6] + R
        dq = quat_log(quat_mul(q_meas, (q[0], -q[1], -q[2], -q[3])))
        nu = np.array([t_meas[0] - t[0], t_meas[1] - t[1], t_meas[2] - t[2], *dq])
        # One solve gives Kᵀ = S⁻¹ Pxzᵀ and S⁻¹ ν.
        X = spd_solve(S, np.concatenate([Pxz.T, nu[:, None]], axis=1))
        S_inv_nu = X[:, n]
        d2 = float(nu @ S_inv_nu)
        accept = d2 <= gate
    reinit = not accept and rejected_run >= reinit_after - 1
    if not initialized or reinit:  # take the pose: state = pose, covariance = R
        if cov.shape[0] == 6:
            cov_new = R.copy()
        else:
            cov_new = np.zeros_like(cov)
            cov_new[:6, :6] = R
            cov_new[6:, 6:] = cov[6:, 6:]
        t_new, q_new, extra_new = t_meas, q_meas, extra.copy()
    elif accept:  # fuse: x ⊞ K ν, P − Pxz S⁻¹ Pxzᵀ
        delta = Pxz @ S_inv_nu
        dq = quat_exp((delta[3], delta[4], delta[5]))
        t_new = (t[0] + delta[0], t[1] + delta[1], t[2] + delta[2])
        q_new = quat_mul(dq, q)
        extra_new = extra + delta[6:]
        down = cov - Pxz @ X[:, :n]
        cov_new = 0.5 * (down + down.T)
    else:  # rejected: the state stays
        t_new, q_new, extra_new, cov_new = t, q, extra.copy(), cov.copy()
    rejected = not accept
    run = rejected_run + 1 if rejected and not reinit else 0
    return PoseUpdate(
        t_new,
        normalized(q_new),
        extra_new,
        cov_new,
        True,
        run,
        accept or reinit,
        int(rejected),
        int(reinit),
    )


class NumpyBackend(FilterBackend):
    """The single-track steps in NumPy and Python floats (registered as ``"numpy"``)."""

    name = "numpy"
    velocity_predict = staticmethod(velocity_predict)
    velocity_update = staticmethod(velocity_update)
    pivot_noise = staticmethod(pivot_noise)
    pose_predict = staticmethod(pose_predict)
    pose_update = staticmethod(pose_update)
