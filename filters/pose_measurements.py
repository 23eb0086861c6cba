"""The pose filters' measurement updates in torch, batched over B tracks: a gated pose, a range
along a direction, a pose aligned from the filter's own, a twist.

A state is a pose ``(t (B,3) m, q (B,4) wxyz)``, further entries ``extra`` (B,k) (a velocity
bias, or the twist of the constant-velocity filter) and a covariance (B,n,n), n = 6 + k, over
the tangent ``[δt, δθ, δextra]`` with left rotation perturbations (:mod:`ukf`). Every function
is pure and branch-free on tensor values (ONNX); the filters' stateful methods check the
inputs and store the results.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evtrack.filters.lie import pose_boxminus, pose_boxplus
from evtrack.filters.linalg import spd_inverse, spd_solve, symmetrize
from evtrack.filters.ukf import UnscentedParams, quat_mean, sigma_offsets, weighted_cov

__all__ = [
    "PoseState",
    "aligned_update",
    "gated_pose_update",
    "range_update",
    "reinit_cov",
    "twist_update",
]

#: ``(t, q, extra, cov)`` of B tracks.
PoseState = tuple[Tensor, Tensor, Tensor, Tensor]


def gated_pose_update(
    state: PoseState,
    initialized: Tensor,
    rejected_run: Tensor,
    t_meas: Tensor,
    q_meas: Tensor,
    cov_meas: Tensor,
    valid: Tensor,
    gate: Tensor,
    reinit_after: int,
    sigma: UnscentedParams | None,
) -> tuple[Tensor, ...]:
    """The gated unscented pose update with ``h(x) = pose``.

    ``ν = (t_m, q_m) ⊟ z̄``; accepted where the track is fresh (the pose is taken: state =
    pose, covariance ``R``) or ``νᵀ S⁻¹ ν <= gate`` (fused); after ``reinit_after`` rejections
    in a row the next rejected pose is taken.

    Args:
        state: the prior. initialized: (B,) bool. rejected_run: (B,) int64.
        t_meas: (B,3) m. q_meas: (B,4) wxyz (either sign). cov_meas: (B,6,6) ``R`` (m², rad²).
        valid: (B,) bool; a pose is missing where not valid or not finite.
        gate: () the χ² gate. reinit_after: see above.
        sigma: the sigma-point parameters, or ``None`` for the closed form: symmetric sigma
            points through ``h(x) = pose`` give ``z̄ = x̄`` and ``S = P_pp + R`` exactly.

    Returns:
        ``(t, q, extra, cov, initialized, rejected_run, used, rejected, reinitialised)``, the
        last three (B,) flags of this update (``used`` bool, the others int64).
    """
    t, q, extra, cov = state
    n = cov.shape[-1]
    # A pose is missing where not valid or not finite; nothing below selects from its
    # (possibly NaN) values then, so they need no masking.
    finite = torch.isfinite(t_meas.sum(-1) + q_meas.sum(-1) + cov_meas.sum((-2, -1)))
    ok = valid & finite
    q_meas = q_meas / torch.linalg.vector_norm(q_meas, dim=-1, keepdim=True)
    R = cov_meas
    if sigma is not None:
        offs = sigma_offsets(cov, sigma.gamma)  # (B,S,n)
        ts, qs = pose_boxplus(t.unsqueeze(1), q.unsqueeze(1), offs[..., :6])
        zt = (sigma.w_mean.unsqueeze(-1) * ts).sum(1)
        zq, eq = quat_mean(qs, sigma.w_mean, q, sigma.mean_iterations)
        dz = torch.cat([ts - zt.unsqueeze(1), eq], dim=-1)  # Zᵢ ⊟ z̄, (B,S,6)
        S = weighted_cov(dz, dz, sigma.w_cov) + R
        Pxz = weighted_cov(offs, dz, sigma.w_cov)  # χᵢ ⊟ x̄ are the offsets themselves
    else:
        # h(x) = pose: symmetric sigma points give z̄ = x̄ and Zᵢ ⊟ z̄ = offsets, hence:
        zt, zq = t, q
        Pxz = cov if n == 6 else cov[:, :, :6]
        S = (cov if n == 6 else cov[:, :6, :6]) + R
    nu = pose_boxminus(t_meas, q_meas, zt, zq)  # (B,6)
    # One solve gives Kᵀ = S⁻¹ Pxzᵀ and S⁻¹ ν.
    X = spd_solve(S, torch.cat([Pxz.transpose(-1, -2), nu.unsqueeze(-1)], dim=-1))
    S_inv_nu = X[..., n:]
    d2 = (nu.unsqueeze(-2) @ S_inv_nu).reshape(-1)  # νᵀ S⁻¹ ν
    delta = (Pxz @ S_inv_nu).squeeze(-1)  # K ν
    cov_up = symmetrize(cov - Pxz @ X[..., :n])  # P − K S Kᵀ = P − Pxz S⁻¹ Pxzᵀ
    t_up, q_up = pose_boxplus(t, q, delta if n == 6 else delta[:, :6])
    extra_up = extra + delta[:, 6:]

    fresh = ~initialized
    accept = ok & (fresh | (d2 <= gate))
    reject = ok & ~accept
    reinit = reject & (rejected_run >= reinit_after - 1)
    take = ok & fresh | reinit
    fuse = accept & ~fresh
    take1, fuse1 = take.unsqueeze(-1), fuse.unsqueeze(-1)
    take2, fuse2 = take1.unsqueeze(-1), fuse1.unsqueeze(-1)
    t_new = torch.where(take1, t_meas, torch.where(fuse1, t_up, t))
    q_new = torch.where(take1, q_meas, torch.where(fuse1, q_up, q))
    q_new = q_new / torch.linalg.vector_norm(q_new, dim=-1, keepdim=True)
    extra_new = torch.where(fuse1, extra_up, extra)
    cov_new = torch.where(take2, reinit_cov(cov, R), torch.where(fuse2, cov_up, cov))
    run = torch.where(reject & ~reinit, rejected_run + 1, torch.where(ok, 0, rejected_run))
    used = fuse | take
    return (
        t_new,
        q_new,
        extra_new,
        cov_new,
        initialized | ok,
        run,
        used,
        reject.long(),
        reinit.long(),
    )


def range_update(
    state: PoseState,
    initialized: Tensor,
    u: Tensor,
    z: Tensor,
    r: Tensor,
    valid: Tensor,
    gate_chi2: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The exact Kalman update with the position's component along a direction, ``z = uᵀ t``
    (``H = [uᵀ, 0]``), covariance in Joseph form; see :meth:`PoseUKF.update_range`.

    Args:
        state: the prior. initialized: (B,) bool (only initialised tracks are updated).
        u: (B,3) direction (normalised here). z: (B,) m. r: (B,) m², the noise variance.
        valid: (B,) bool. gate_chi2: the gate of ``ν² / S``.

    Returns:
        The new ``(t, q, extra, cov)`` and (B,) bool, True where the range was used.
    """
    t, q, extra, P = state
    B, n = P.shape[0], P.shape[-1]
    kw = {"dtype": t.dtype, "device": t.device}
    norm = torch.linalg.vector_norm(u, dim=-1)
    ok = (valid & initialized & torch.isfinite(u).all(-1) & (norm > 0)
          & torch.isfinite(z) & torch.isfinite(r) & (r > 0))
    u = u / torch.where(norm > 0, norm, torch.ones_like(norm)).unsqueeze(-1)
    H = torch.zeros(B, n, **kw)
    H[:, :3] = u
    PH = (P @ H.unsqueeze(-1)).squeeze(-1)  # (B,n) = P Hᵀ
    S = (H * PH).sum(-1) + r
    nu = z - (u * t).sum(-1)
    S_safe = torch.where(ok & (S > 0), S, torch.ones_like(S))
    passed = ok & (S > 0) & (nu * nu <= gate_chi2 * S_safe)
    K = PH / S_safe.unsqueeze(-1)
    delta = torch.where(passed.unsqueeze(-1), K * nu.unsqueeze(-1), torch.zeros_like(K))
    t_new, q_new = pose_boxplus(t, q, delta[:, :6])
    IKH = torch.eye(n, **kw) - K.unsqueeze(-1) * H.unsqueeze(-2)
    P_new = symmetrize(IKH @ P @ IKH.transpose(-1, -2)
                       + r[:, None, None] * K.unsqueeze(-1) * K.unsqueeze(-2))
    new = _where_passed(passed, (t_new, q_new, extra + delta[:, 6:], P_new), state, keep_t=False)
    return (*new, passed)


def aligned_update(
    state: PoseState,
    initialized: Tensor,
    t_meas: Tensor,
    q_meas: Tensor,
    R: Tensor,
    valid: Tensor,
    gate: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The exact linear update with a pose of the pose part (``H = [I₆, 0]``), gated, covariance
    in Joseph form; see :meth:`PoseUKF.update_aligned`.

    Args:
        state: the prior. initialized: (B,) bool (only initialised tracks are updated).
        t_meas: (B,3) m. q_meas: (B,4) wxyz (either sign). R: (B,6,6) m², rad².
        valid: (B,) bool; non-finite inputs count as missing. gate: () the χ² gate.

    Returns:
        The new ``(t, q, extra, cov)`` and (B,) bool, True where the pose was used.
    """
    t, q, extra, P = state
    B, n = P.shape[0], P.shape[-1]
    kw = {"dtype": t.dtype, "device": t.device}
    finite = torch.isfinite(t_meas.sum(-1) + q_meas.sum(-1) + R.sum((-2, -1)))
    ok = valid & finite & initialized
    zeros6 = torch.zeros(B, 6, **kw)
    eye6 = torch.eye(6, **kw).expand(B, 6, 6)
    t_in = torch.where(ok.unsqueeze(-1), t_meas, t)  # no NaN reaches the arithmetic
    q_in = torch.where(ok.unsqueeze(-1), q_meas, q)
    R = torch.where(ok[:, None, None], R, eye6)
    q_in = q_in / torch.linalg.vector_norm(q_in, dim=-1, keepdim=True)
    nu = torch.where(ok.unsqueeze(-1), pose_boxminus(t_in, q_in, t, q), zeros6)
    S = symmetrize(P[:, :6, :6] + R)
    Pxz = P[:, :, :6]
    X = spd_solve(S, torch.cat([Pxz.transpose(-1, -2), nu.unsqueeze(-1)], dim=-1))
    K = X[..., :n].transpose(-1, -2)  # (B,n,6) = P Hᵀ S⁻¹
    d2 = (nu.unsqueeze(-2) @ X[..., n:]).reshape(-1)
    passed = ok & (d2 <= gate)
    delta = (K @ nu.unsqueeze(-1)).squeeze(-1)
    t_new, q_new = pose_boxplus(t, q, delta[:, :6])
    H = torch.zeros(B, 6, n, **kw)
    H[:, :, :6] = torch.eye(6, **kw)
    IKH = torch.eye(n, **kw) - K @ H
    P_new = symmetrize(IKH @ P @ IKH.transpose(-1, -2) + K @ R @ K.transpose(-1, -2))
    new = _where_passed(passed, (t_new, q_new, extra + delta[:, 6:], P_new), state)
    return (*new, passed)


def twist_update(
    state: PoseState,
    twist_meas: Tensor,
    cov_meas: Tensor,
    valid: Tensor,
    default_cov: Tensor,
) -> PoseState:
    """The update with a measured twist of a state whose ``extra`` is the twist: ``h(x) = V``
    is linear, so the unscented transform is exact and equals the Kalman update
    ``S = P_VV + R``, ``K = P_xV S⁻¹``.

    Args:
        state: the prior, ``extra`` (B,6) the twist ``[v_o (m/s), ω (rad/s)]``, cov (B,12,12).
        twist_meas: (B,6). cov_meas: (B,6,6). valid: (B,) bool; non-finite measurements are
            skipped. default_cov: (6,6) the covariance used in place of a skipped one's.

    Returns:
        The new ``(t, q, twist, cov)``.
    """
    t, q, twist, cov = state
    ok = (
        valid & torch.isfinite(twist_meas).all(-1) & torch.isfinite(cov_meas).flatten(1).all(-1)
    )
    R = torch.where(ok[:, None, None], cov_meas, default_cov)
    S = cov[:, 6:, 6:] + R
    Pxz = cov[:, :, 6:]
    K = Pxz @ spd_inverse(S)
    nu = torch.where(ok.unsqueeze(-1), twist_meas, twist) - twist
    delta = (K @ nu.unsqueeze(-1)).squeeze(-1)
    t_up, q_up = pose_boxplus(t, q, delta[:, :6])
    cov_up = symmetrize(cov - K @ Pxz.transpose(-1, -2))
    q_up = q_up / q_up.norm(dim=-1, keepdim=True)
    return _where_passed(ok, (t_up, q_up, twist + delta[:, 6:], cov_up), state)


def reinit_cov(cov: Tensor, R: Tensor) -> Tensor:
    """The covariance after re-initialising on a pose: ``R`` for the pose block, the old
    covariance for any further state (the twist), no cross terms."""
    n = cov.shape[-1]
    if n == 6:
        return R
    top = torch.cat([R, torch.zeros_like(cov[:, :6, 6:])], dim=-1)
    bottom = torch.cat([torch.zeros_like(cov[:, 6:, :6]), cov[:, 6:, 6:]], dim=-1)
    return torch.cat([top, bottom], dim=-2)


def _where_passed(passed: Tensor, new: PoseState, old: PoseState, keep_t: bool = True
                  ) -> PoseState:
    """``new`` where ``passed`` (B,), else ``old``; ``keep_t=False`` takes the new ``t``
    everywhere (an update whose step is zero where it did not pass)."""
    keep = passed.unsqueeze(-1)
    t = torch.where(keep, new[0], old[0]) if keep_t else new[0]
    return (t, torch.where(keep, new[1], old[1]), torch.where(keep, new[2], old[2]),
            torch.where(keep.unsqueeze(-1), new[3], old[3]))
