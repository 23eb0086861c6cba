"""The compiled (numba) backend: the velocity update and the pose predict of :mod:`fast_path`
compiled, and runs of many steps in one call.

:func:`evtrack.filters.fast_path.velocity_update` in NumPy spends most of its ~200 µs (16 RoIs)
in the dispatch of ~80 tiny array operations and three LAPACK calls, not in arithmetic. The
kernel here runs the same update in one compiled loop nest: the RoI selection, the measurement
rows, the Laplacian weighting passes and the information-form posterior, with the 6x6 algebra
by an unpivoted Cholesky factorisation written out (the matrices are symmetric positive
definite, as LAPACK ``posv`` assumes too). Same formulas and row order as the NumPy form; the
results agree with it and with the torch steps to rounding
(``tests/filters/test_backend_parity.py`` runs every backend). Per call with 16 RoIs (a
tracker's step): 63 µs against 197 µs for the NumPy form, 400 RoIs: 107 against 265 µs
(``benchmarks/bench_filters.py``, columns ``fast call`` and ``fast NumPy``); the kernel itself
takes ~12 µs of the 63, the rest is the filter's input checks and conversions.

The pose predict (:func:`pose_predict`) is the closed-form unscented predict of
:func:`evtrack.filters.fast_path.pose_predict` on the filter's arrays, with the quaternion and
SE(3) algebra of :mod:`scalar_lie` compiled into it: ~7 µs per call against ~30 µs for the
NumPy form (the filter's whole ``predict`` call: 114 -> 36 µs).

A tracker between two RGB frames runs tens of velocity steps whose inputs are all known in
advance: :func:`velocity_run` does them in one call (the decaying predict and the update of
each step, in order, stopping before a step whose matrix is not positive definite), so the
~50 µs of per-call checks and conversions are paid once per run, not per step;
:func:`pose_predict_run` does the same for the pose predicts. Their results equal the
step-by-step calls bit for bit (``tests/filters/test_backend_parity.py``).

:class:`NumbaBackend` (registered as ``"numba"`` in :mod:`backends`) takes the NumPy backend's
other steps. Where numba is missing (:func:`available`) the NumPy backend runs instead. The
first use compiles the kernels (10-15 s); numba caches them on disk (``__pycache__`` beside
this file, or ``NUMBA_CACHE_DIR``), so later processes load them in a fraction of a second.

Shapes drop the batch dimension, as in :mod:`fast_path`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from evtrack.filters.backend_base import RoiRows, VelocityModel
from evtrack.filters.fast_path import NumpyBackend
from evtrack.filters.scalar_lie import normalized, quat_mul, quat_rotate, rotation_matrix, se3_exp
from evtrack.runtime.jit import available as _numba_available
from evtrack.runtime.jit import njit as _njit

__all__ = [
    "NumbaBackend",
    "available",
    "pose_predict",
    "pose_predict_run",
    "velocity_run",
    "velocity_update",
]

_TINY = float(np.finfo(np.float64).tiny)
_NUMBA = _numba_available()  # whether numba compiles the kernels here
_NOT_PD = -1  # status of a factorisation that met a non-positive pivot


def available() -> bool:
    """Whether the compiled kernels can run (numba is installed)."""
    return _numba_available()


def _inlined(fn: Callable) -> Callable:
    """``fn`` compiled into each kernel that calls it (numba's ``inline="always"``: the
    kernels split into such helpers run as fast as written in one piece), or ``fn`` itself
    where numba is missing."""
    if not _numba_available():
        return fn
    import numba

    return numba.njit(inline="always", cache=True, nogil=True)(fn)


@_njit
def _cholesky(A, L):
    """Lower Cholesky factor of the symmetric (n, n) ``A`` (its lower triangle is read) into
    ``L``; returns 0, or :data:`_NOT_PD` if a pivot is not positive (or not finite)."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:  # NaN too
            return _NOT_PD
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
        for i in range(j):
            L[i, j] = 0.0
    return 0


@_njit
def _solve_into(L, b, x):
    """``x = (L Lᵀ)⁻¹ b`` for a vector ``b`` (n,)."""
    n = L.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]


@_njit
def _inverse_into(L, out):
    """``out = (L Lᵀ)⁻¹``, made exactly symmetric."""
    n = L.shape[0]
    e = np.zeros(n)
    col = np.empty(n)
    for j in range(n):
        e[:] = 0.0
        e[j] = 1.0
        _solve_into(L, e, col)
        out[:, j] = col
    for i in range(n):
        for j in range(i):
            v = 0.5 * (out[i, j] + out[j, i])
            out[i, j] = v
            out[j, i] = v


@_njit
def _laplacian_weights(residual, M, fixed_scale, scale, scale_min, floor, previous, has_previous,
                       rho):
    """Row weights ``ρ = max(exp(-|r - med|/b), min(2 b floor, 1))`` of the first ``M`` rows
    (:func:`evtrack.filters.fast_path.laplacian_weights`) into ``rho``."""
    if M == 0:
        return
    dev = np.sort(residual[:M])
    med = dev[(M - 1) // 2]  # the lower median
    total = 0.0
    weighted = 0.0
    weights = 0.0
    for m in range(M):
        d = abs(residual[m] - med)
        rho[m] = d
        total += d
        if has_previous:
            weighted += previous[m] * d
            weights += previous[m]
    if fixed_scale:
        b = scale
    else:
        b = weighted / max(weights, _TINY) if has_previous else total / M
        b = max(b, scale_min)
    low = min(2.0 * b * floor, 1.0)
    for m in range(M):
        rho[m] = max(math.exp(rho[m] / -b), low)


@_inlined
def _usable_rows(normal_flow, uv, depth, flow, normal, mask, usable):
    """Mark in ``usable`` (N,) the RoIs that enter an update: unmasked, with a depth in
    (0, inf), a finite pixel and flow and, under the normal-flow constraint, a direction (a
    non-zero flow where it is normal-only). Returns the counts of RoIs unmasked and of those
    with a usable depth."""
    n_mask = 0
    n_depth = 0
    for i in range(depth.shape[0]):
        if not mask[i]:
            continue
        n_mask += 1
        z = depth[i]
        if not (z > 0.0 and z < math.inf):
            continue
        n_depth += 1
        if (math.isfinite(uv[i, 0]) and math.isfinite(uv[i, 1]) and math.isfinite(flow[i, 0])
                and math.isfinite(flow[i, 1])):
            # a zero normal flow has no direction (dropped under the constraint)
            mag = math.sqrt(flow[i, 0] * flow[i, 0] + flow[i, 1] * flow[i, 1])
            usable[i] = mag > 0.0 or not (normal_flow and normal[i])
    return n_mask, n_depth


@_inlined
def _row_count(normal_flow, normal, rows):
    """The number of measurement rows of the RoIs ``rows``: one along each flow, one across
    each full flow."""
    n_valid = rows.shape[0]
    n_across = 0
    for r in range(n_valid):
        if not normal_flow or not normal[rows[r]]:
            n_across += 1
    return n_valid + n_across


@_inlined
def _write_row(HT, m, a, b, x, y, iz):
    """Column ``m`` of ``Hᵀ``: the row ``[a/Z, b/Z, −p/Z, −(y p + b), a + x p, b x − a y]``,
    ``p = a x + b y``, of a flow direction ``e`` with ``a = e_u fx``, ``b = e_v fy`` at the
    normalised pixel ``(x, y)`` with ``iz = 1/Z``."""
    p = a * x + b * y
    HT[0, m] = a * iz
    HT[1, m] = b * iz
    HT[2, m] = -(p * iz)
    HT[3, m] = -(y * p + b)
    HT[4, m] = x * p + a
    HT[5, m] = b * x - a * y


@_inlined
def _measurement_rows(normal_flow, normal_info, fx, fy, cx, cy, uv, depth, flow, normal, rows,
                      HT, zval, row_info):
    """Fill ``Hᵀ`` (6, M), the row values ``zval`` (M,) (zeros before) and the rows'
    information ``row_info`` (M,) (a full flow's ``R⁻¹`` before) of the RoIs ``rows``: along
    ``n = F/|F|`` for every RoI (value ``|F|``), then across ``n⊥`` for the full flows (value
    0); a zero full flow takes the image axes."""
    n_valid = rows.shape[0]
    across = n_valid
    for r in range(n_valid):
        i = rows[r]
        x = (uv[i, 0] - cx) / fx
        y = (uv[i, 1] - cy) / fy
        iz = 1.0 / depth[i]
        mag = math.sqrt(flow[i, 0] * flow[i, 0] + flow[i, 1] * flow[i, 1])
        if mag > 0.0:
            nx = flow[i, 0] * (1.0 / mag)
            ny = flow[i, 1] * (1.0 / mag)
        else:  # the image axes
            nx = 1.0
            ny = 0.0
        zval[r] = mag
        _write_row(HT, r, nx * fx, ny * fy, x, y, iz)  # along n
        if normal_flow and normal[i]:
            row_info[r] = normal_info
        else:  # across: n⊥ = (-ny, nx)
            _write_row(HT, across, -ny * fx, nx * fy, x, y, iz)
            across += 1


@_inlined
def _innovations(twist, reference, HT, zval, against_reference, innovation, residual):
    """Fill the innovations ``z − H V`` (M,) and the first weighting pass's residuals: against
    the ``reference`` twist if ``against_reference``, else the innovations again."""
    for m in range(zval.shape[0]):
        h_twist = 0.0
        h_ref = 0.0
        for k in range(6):
            h_twist += twist[k] * HT[k, m]
            h_ref += reference[k] * HT[k, m]
        innovation[m] = zval[m] - h_twist
        residual[m] = zval[m] - (h_ref if against_reference else h_twist)


@_inlined
def _information(HT, row_info, rho, innovation, prior_info, info, gain):
    """``info = Hᵀ W H + P⁻¹`` (6, 6) and ``gain = Hᵀ W ν`` (6,) with ``W = R⁻¹ ρ``."""
    M = innovation.shape[0]
    for j in range(6):
        g = 0.0
        for m in range(M):
            g += HT[j, m] * row_info[m] * rho[m] * innovation[m]
        gain[j] = g
        for k in range(j + 1):
            s = 0.0
            for m in range(M):
                s += HT[j, m] * row_info[m] * rho[m] * HT[k, m]
            info[j, k] = s + prior_info[j, k]
            info[k, j] = info[j, k]


@_inlined
def _next_residuals(L, gain, twist, HT, zval, post_twist, step, residual):
    """A weighting pass before the last: the twist ``V + Λ⁻¹ Hᵀ W ν`` (``L``: the Cholesky
    factor of ``Λ``) into ``post_twist``, and the next pass's residuals ``z − H V⁺``."""
    _solve_into(L, gain, step)
    for k in range(6):
        post_twist[k] = twist[k] + step[k]
    for m in range(zval.shape[0]):
        h = 0.0
        for k in range(6):
            h += post_twist[k] * HT[k, m]
        residual[m] = zval[m] - h


@_inlined
def _posterior(L, gain, twist, post_twist, post_cov):
    """The last pass: ``P⁺ = Λ⁻¹`` (exactly symmetric) and ``V⁺ = V + P⁺ Hᵀ W ν``."""
    _inverse_into(L, post_cov)
    for j in range(6):
        s = 0.0
        for k in range(6):
            s += post_cov[j, k] * gain[k]
        post_twist[j] = twist[j] + s


@_njit
def _update_kernel(normal_flow, weighting, reference_previous, passes, fixed_scale, flow_info,
                   normal_info, scale, scale_min, floor, fx, fy, cx, cy, twist, cov, reference,
                   uv, depth, flow, normal, mask):
    """The update of :func:`velocity_update` on contiguous arrays; returns the posterior and
    the skip counts, or the prior and ``(-1, 0)`` where a 6x6 is not positive definite."""
    usable = np.zeros(depth.shape[0], np.bool_)
    n_mask, n_depth = _usable_rows(normal_flow, uv, depth, flow, normal, mask, usable)
    rows = np.flatnonzero(usable)
    # measurement rows: along n for every RoI, then across n⊥ for the full flows
    M = _row_count(normal_flow, normal, rows)
    HT = np.empty((6, M))
    zval = np.zeros(M)
    row_info = np.full(M, flow_info)  # R⁻¹ per row: the normal-only rows' own
    _measurement_rows(normal_flow, normal_info, fx, fy, cx, cy, uv, depth, flow, normal, rows,
                      HT, zval, row_info)
    L = np.empty((6, 6))
    prior_info = np.empty((6, 6))
    if _cholesky(cov, L):
        return twist, cov, -1, 0
    _inverse_into(L, prior_info)
    innovation = np.empty(M)
    residual = np.empty(M)
    _innovations(twist, reference, HT, zval, weighting and reference_previous, innovation,
                 residual)
    rho = np.ones(M)
    previous = np.ones(M)
    info = np.empty((6, 6))
    gain = np.empty(6)
    step = np.empty(6)
    post_twist = twist.copy()
    post_cov = np.empty((6, 6))
    n_passes = passes if weighting else 1
    for it in range(n_passes):
        if weighting:
            previous[:] = rho
            _laplacian_weights(residual, M, fixed_scale, scale, scale_min, floor, previous,
                               it > 0, rho)
        _information(HT, row_info, rho, innovation, prior_info, info, gain)
        if _cholesky(info, L):
            return twist, cov, -1, 0
        if it + 1 < n_passes:  # only the twist: the next pass's residuals
            _next_residuals(L, gain, twist, HT, zval, post_twist, step, residual)
        else:
            _posterior(L, gain, twist, post_twist, post_cov)
    return post_twist, post_cov, n_mask - n_depth, n_depth - rows.shape[0]


def _settings(model: VelocityModel) -> tuple[bool | int | float, ...]:
    """The scalar leading arguments of :func:`_update_kernel` (and of the run kernel): the
    config's switches, the ``consts`` noises and weighting scales, the intrinsics."""
    cfg, consts, focal, principal = model
    _, flow_info, scale, scale_min, floor, normal_info = consts
    return (bool(cfg.normal_flow), bool(cfg.weighting), cfg.weighting_reference == "previous",
            int(cfg.weighting_iterations), cfg.laplace_scale is not None, float(flow_info),
            float(normal_info), float(scale), float(scale_min), float(floor), float(focal[0]),
            float(focal[1]), float(principal[0]), float(principal[1]))


def _roi_arrays(model: VelocityModel, rois: RoiRows) -> tuple[np.ndarray, ...]:
    """The RoI inputs as the kernels take them: contiguous float64 ``uv`` (N,2), ``depth``
    (N,), ``flow`` (N,2), and bool ``normal`` (N,) (``assume_normal`` where not given)."""
    f64 = np.float64
    uv, depth, flow, normal_only, _ = rois
    normal = (np.full(depth.shape[0], model.config.assume_normal) if normal_only is None
              else normal_only)
    return (np.ascontiguousarray(uv, f64), np.ascontiguousarray(depth, f64),
            np.ascontiguousarray(flow, f64), np.ascontiguousarray(normal, np.bool_))


def velocity_update(
    model: VelocityModel, twist: np.ndarray, cov: np.ndarray, reference: np.ndarray,
    rois: RoiRows,
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """:func:`evtrack.filters.fast_path.velocity_update` compiled (same arguments and
    results); needs numba (:func:`available`).

    Raises:
        numpy.linalg.LinAlgError: if a 6x6 matrix is not positive definite.
    """
    f64 = np.float64
    mask = rois.mask
    mask = np.ones(rois.depth.shape[0], np.bool_) if mask is None else mask
    post_twist, post_cov, skipped_depth, skipped_flow = _update_kernel(
        *_settings(model), np.ascontiguousarray(twist, f64), np.ascontiguousarray(cov, f64),
        np.ascontiguousarray(reference, f64), *_roi_arrays(model, rois),
        np.ascontiguousarray(mask, np.bool_))
    if skipped_depth < 0:
        raise np.linalg.LinAlgError("a 6x6 information matrix is not positive definite")
    return post_twist, post_cov, skipped_depth, skipped_flow


@_njit
def _velocity_run_kernel(normal_flow, weighting, reference_previous, passes, fixed_scale,
                         flow_info, normal_info, scale, scale_min, floor, fx, fy, cx, cy,
                         log_rate, q_matrix, twist, cov, reference, dts, bounds, uv, depth,
                         flow, normal):
    """``n = len(dts)`` steps of predict then update (rows ``bounds[k]:bounds[k+1]``; a step
    without rows only predicts), stopping before a step whose update meets a matrix that is
    not positive definite. Returns the number of steps done and, per step, the twist (n,6),
    covariance (n,6,6), reference (n,6) and skipped (depth, flow) counts (n,2)."""
    n = dts.shape[0]
    twists = np.empty((n, 6))
    covs = np.empty((n, 6, 6))
    refs = np.empty((n, 6))
    skipped = np.zeros((n, 2), np.int64)
    ones = np.ones(uv.shape[0], np.bool_)
    for k in range(n):
        decay = math.exp(dts[k] * log_rate)  # as fast_path.velocity_predict
        twist = twist * decay
        cov = cov * (decay * decay) + dts[k] * q_matrix
        lo, hi = bounds[k], bounds[k + 1]
        if hi > lo:
            post_twist, post_cov, skipped_depth, skipped_flow = _update_kernel(
                normal_flow, weighting, reference_previous, passes, fixed_scale, flow_info,
                normal_info, scale, scale_min, floor, fx, fy, cx, cy, twist, cov, reference,
                uv[lo:hi], depth[lo:hi], flow[lo:hi], normal[lo:hi], ones[lo:hi])
            if skipped_depth < 0:
                return k, twists, covs, refs, skipped
            twist, cov, reference = post_twist, post_cov, post_twist
            skipped[k, 0] = skipped_depth
            skipped[k, 1] = skipped_flow
        twists[k] = twist
        covs[k] = cov
        refs[k] = reference
    return n, twists, covs, refs, skipped


def velocity_run(
    model: VelocityModel, q_matrix: np.ndarray, twist: np.ndarray, cov: np.ndarray,
    reference: np.ndarray, dts: np.ndarray, bounds: np.ndarray, rois: RoiRows,
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` steps of :func:`evtrack.filters.fast_path.velocity_predict` then
    :func:`velocity_update` in one call, with the same arithmetic (arguments and results as
    :meth:`FilterBackend.velocity_run`)."""
    f64 = np.float64
    return _velocity_run_kernel(
        *_settings(model), float(model.consts[0]), np.ascontiguousarray(q_matrix, f64),
        np.ascontiguousarray(twist, f64), np.ascontiguousarray(cov, f64),
        np.ascontiguousarray(reference, f64), np.ascontiguousarray(dts, f64).reshape(-1),
        np.ascontiguousarray(bounds, np.int64), *_roi_arrays(model, rois))


@_inlined
def _times_transition(M, rot, db, out, transposed):
    """``A M`` for an (n, n) ``M`` and the pose predict's transition ``A = diag(R, R)`` (n = 6)
    or, with a velocity bias, ``[[R, 0, db I], [0, R, 0], [0, 0, I]]`` (n = 9): each 3-row
    block of the pose rotated by ``rot`` (3, 3), ``db`` times the bias rows added to the
    position's. Into ``out`` (n, n), or its transpose where ``transposed``."""
    n = M.shape[0]
    for i in range(n):
        b, k = (i // 3) * 3, i % 3
        for j in range(n):
            if i >= 6:
                v = M[i, j]
            else:
                v = rot[k, 0] * M[b, j] + rot[k, 1] * M[b + 1, j] + rot[k, 2] * M[b + 2, j]
                if n > 6 and i < 3:
                    v += db * M[6 + i, j]
            if transposed:
                out[j, i] = v
            else:
                out[i, j] = v


@_njit
def _pose_predict_kernel(t, q, cov, twist, dt, q_matrix, bias):
    """:func:`evtrack.filters.fast_path.pose_predict` on arrays: ``t`` (1,3), ``q`` (1,4),
    ``cov`` (1,n,n), ``twist`` (1,6), ``q_matrix`` (n,n), ``bias`` (1,k) (``k = n - 6``: 0, or
    3 for a velocity bias) -> new (1,3), (1,4), (1,n,n)."""
    n = cov.shape[1]
    w = twist[0]
    qd, pd = se3_exp((w[0] * dt, w[1] * dt, w[2] * dt), (w[3] * dt, w[4] * dt, w[5] * dt))
    r = quat_rotate(qd, (t[0, 0], t[0, 1], t[0, 2]))
    t_out = np.empty((1, 3))
    t_out[0, 0], t_out[0, 1], t_out[0, 2] = r[0] + pd[0], r[1] + pd[1], r[2] + pd[2]
    db = 0.0  # the bias's share of the step: dt times the origin's speed |v_o + ω × t|
    if n > 6:  # t' = R t + p + b db
        cx = w[0] + w[4] * t[0, 2] - w[5] * t[0, 1]
        cy = w[1] + w[5] * t[0, 0] - w[3] * t[0, 2]
        cz = w[2] + w[3] * t[0, 1] - w[4] * t[0, 0]
        db = dt * math.sqrt(cx * cx + cy * cy + cz * cz)
        for i in range(3):
            t_out[0, i] += bias[0, i] * db
    qn = normalized(quat_mul(qd, (q[0, 0], q[0, 1], q[0, 2], q[0, 3])))
    q_out = np.empty((1, 4))
    q_out[0, 0], q_out[0, 1], q_out[0, 2], q_out[0, 3] = qn
    rows = rotation_matrix(qd)
    rot = np.empty((3, 3))
    for i in range(3):
        rot[i, 0], rot[i, 1], rot[i, 2] = rows[i]
    # A P Aᵀ with A = diag(R, R) (and, with a bias, A = [[R, 0, db I], [0, R, 0], [0, 0, I]]):
    # (A P)ᵀ, then ((A P) Aᵀ)ᵀ = A (A P)ᵀ
    half_t = np.empty((n, n))
    _times_transition(cov[0], rot, db, half_t, True)
    full_t = np.empty((n, n))
    _times_transition(half_t, rot, db, full_t, False)
    cov_out = np.empty((1, n, n))
    for i in range(n):
        for j in range(n):
            cov_out[0, i, j] = 0.5 * (full_t[j, i] + full_t[i, j]) + dt * q_matrix[i, j]
    return t_out, q_out, cov_out


@_njit
def _pose_predict_run_kernel(t, q, cov, twists, dts, q_matrix, bias):
    """:func:`_pose_predict_kernel` ``m`` times in a row: step ``k`` by ``twists[k]`` over
    ``dts[k]`` (the bias, unchanged by a predict, the same for all); returns the states after
    each step, (m,1,3), (m,1,4), (m,1,n,n)."""
    m = twists.shape[0]
    n = cov.shape[1]
    t_all = np.empty((m, 1, 3))
    q_all = np.empty((m, 1, 4))
    cov_all = np.empty((m, 1, n, n))
    for k in range(m):
        t, q, cov = _pose_predict_kernel(t, q, cov, twists[k:k + 1], dts[k], q_matrix, bias)
        t_all[k] = t
        q_all[k] = q
        cov_all[k] = cov
    return t_all, q_all, cov_all


def _bias_array(bias: np.ndarray | None) -> np.ndarray:
    """A velocity bias (1,3) m/s as the kernels take it; (1,0) without one."""
    return np.zeros((1, 0)) if bias is None else np.ascontiguousarray(bias, np.float64)


def pose_predict_run(t: np.ndarray, q: np.ndarray, cov: np.ndarray, twists: np.ndarray,
                     dts: np.ndarray, q_matrix: np.ndarray, bias: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`pose_predict` for ``m`` steps in one call (the same arithmetic, bit for bit):
    ``twists`` (m,6), ``dts`` (m,) s; returns the states after each step, ``t`` (m,1,3),
    ``q`` (m,1,4), ``cov`` (m,1,n,n). Needs numba (:func:`available`)."""
    f64 = np.float64
    return _pose_predict_run_kernel(
        np.ascontiguousarray(t, f64), np.ascontiguousarray(q, f64),
        np.ascontiguousarray(cov, f64), np.ascontiguousarray(twists, f64).reshape(-1, 6),
        np.ascontiguousarray(dts, f64).reshape(-1), np.ascontiguousarray(q_matrix, f64),
        _bias_array(bias))


def pose_predict(t: np.ndarray, q: np.ndarray, cov: np.ndarray, twist: np.ndarray, dt: float,
                 q_matrix: np.ndarray, bias: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`evtrack.filters.fast_path.pose_predict` compiled (arguments and results as
    :meth:`FilterBackend.pose_predict`). Needs numba (:func:`available`)."""
    f64 = np.float64
    return _pose_predict_kernel(np.ascontiguousarray(t, f64), np.ascontiguousarray(q, f64),
                                np.ascontiguousarray(cov, f64), np.ascontiguousarray(twist, f64),
                                float(dt), np.ascontiguousarray(q_matrix, f64), _bias_array(bias))


class NumbaBackend(NumpyBackend):
    """The NumPy backend with its velocity update and pose predict compiled by numba, and runs
    of many steps per call (registered as ``"numba"``)."""

    name = "numba"
    runs = True
    velocity_update = staticmethod(velocity_update)
    velocity_run = staticmethod(velocity_run)
    pose_predict = staticmethod(pose_predict)
    pose_predict_run = staticmethod(pose_predict_run)

    def available(self) -> bool:
        """Whether numba is installed."""
        return _NUMBA
