"""The pose filters' predicts in torch, batched over B tracks: the specification of
:meth:`PoseUKF.predict_state` and :meth:`PoseTwistUKF.predict_state`.

Each sigma point moves by the exact constant-twist motion (``Ṗ = v_o + ω × P``):
``t' = R_Δ t + p_Δ``, ``q' = q_Δ ⊗ q`` with ``(q_Δ, p_Δ) = exp(dt·V)`` (:func:`lie.se3_exp`),
then ``P += Q·dt`` (``Q`` a noise density, so the filter does not depend on the update rate).
A known twist moves every sigma point by one rigid motion, linear on the tangent
(``δt' = R_Δ δt``, ``δθ' = R_Δ δθ``), so :func:`closed_form_predict` gives the sigma-point
result exactly: ``P' = A P Aᵀ + Q dt``. Every function is branch-free on tensor values (ONNX).
"""

from __future__ import annotations

import torch
from torch import Tensor

from evtrack.filters.lie import pose_boxplus, quat_mul, quat_rotate, se3_exp
from evtrack.filters.linalg import symmetrize
from evtrack.filters.ukf import UnscentedParams, quat_mean, sigma_offsets, weighted_cov

__all__ = [
    "closed_form_predict",
    "origin_speed",
    "propagate_sigma_points",
    "times_bias_transition",
]


def closed_form_predict(
    t: Tensor,
    q: Tensor,
    cov: Tensor,
    twist: Tensor,
    dt: Tensor,
    q_matrix: Tensor,
    bias: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The unscented predict of a pose moved by a known twist, in closed form.

    Args:
        t: (B,3) m. q: (B,4) wxyz. cov: (B,n,n) over ``[δt, δθ(, δb)]``.
        twist: (B,6) ``[v_o (m/s), ω (rad/s)]``. dt: (B,) s.
        q_matrix: (n,n) process-noise density.
        bias: (B,3) m/s per m/s of the object's speed: the velocity bias of a filter with one
            (n = 9; the position moves further by ``b s dt``, ``s = |v_o + ω × t|`` at the prior
            ``t``), else ``None`` (n = 6).

    Returns:
        ``(t, q, cov)`` after ``dt``.
    """
    # Every sigma point moves by the same rigid motion, which acts on the tangent linearly:
    # δt' = R_Δ δt (+ s dt δb), δθ' = R_Δ δθ (δb' = δb). The unscented transform is exact:
    # P' = A P Aᵀ + Q dt.
    qd, pd = se3_exp(twist * dt.unsqueeze(-1))
    t_prior = t
    t = quat_rotate(qd, t) + pd
    if bias is not None:
        db = dt * origin_speed(twist, t_prior)  # the bias's share of the step: s dt
        t = t + bias * db.unsqueeze(-1)
    q = quat_mul(qd, q)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    # P' = A P Aᵀ with A = diag(R_Δ, R_Δ): rotate the 3-vector blocks of P's rows, then of
    # the columns (elementwise work: batched 6x6 matmuls are slow at large B).
    qb = qd[:, None, None, :]
    if bias is None:
        half = quat_rotate(qb, cov.unflatten(-1, (2, 3))).flatten(-2)  # P Aᵀ
        cov = quat_rotate(qb, half.transpose(-1, -2).unflatten(-1, (2, 3))).flatten(-2)
    else:
        half = times_bias_transition(cov, qb, db)  # P Aᵀ
        cov = times_bias_transition(half.transpose(-1, -2), qb, db)  # A P Aᵀ
    cov = symmetrize(cov) + dt[:, None, None] * q_matrix
    return t, q, cov


def propagate_sigma_points(
    t: Tensor,
    q: Tensor,
    extra: Tensor,
    cov: Tensor,
    twist: Tensor | None,
    dt: Tensor,
    sigma: UnscentedParams,
    q_matrix: Tensor,
    decay_rate: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Unscented predict under a constant twist.

    Args:
        t: (B,3) m. q: (B,4) wxyz. extra: (B,k) the state beyond the pose (a velocity bias
            of the pose-only filter, the twist of the constant-velocity one, or (B,0)).
        cov: (B,n,n), n = 6 + k.
        twist: (B,6) the track's twist (the pose-only filter), or ``None``: each sigma point's
            own, from ``extra`` (the constant-velocity filter).
        dt: (B,) s. sigma: the sigma-point parameters.
        q_matrix: (n,n) or (B,n,n) process-noise densities.
        decay_rate: () ``ln(alpha)/alpha_dt`` (1/s), the decay of a twist in the state
            (``twist=None`` only): ``V' = alpha^(dt/alpha_dt) V``; ``None``: no decay.

    Returns:
        The mean ``(t, q, extra)`` and covariance after ``dt``.
    """
    offs = sigma_offsets(cov, sigma.gamma)
    ts, qs = pose_boxplus(t.unsqueeze(1), q.unsqueeze(1), offs[..., :6])
    es = extra.unsqueeze(1) + offs[..., 6:]
    if twist is None:
        xi = es * dt[:, None, None]  # each sigma point's own twist
        qd, pd = se3_exp(xi)
    else:
        qd, pd = se3_exp(twist * dt.unsqueeze(-1))
        qd, pd = qd.unsqueeze(1), pd.unsqueeze(1)
    ts = quat_rotate(qd, ts) + pd
    if twist is not None and es.shape[-1]:  # a velocity bias: t' = R t + p + b s dt
        ts = ts + es * (dt * origin_speed(twist, t))[:, None, None]
    qs = quat_mul(qd, qs)
    if twist is None and decay_rate is not None:
        es = es * decay_rate.mul(dt).exp()[:, None, None]  # V' = alpha^(dt/alpha_dt) V
    wm = sigma.w_mean.unsqueeze(-1)
    tm = (wm * ts).sum(1)
    qm, eq = quat_mean(qs, sigma.w_mean, qs[:, 0], sigma.mean_iterations)
    em = (wm * es).sum(1)
    dev = torch.cat([ts - tm.unsqueeze(1), eq, es - em.unsqueeze(1)], dim=-1)
    # P = Σ Wc devᵢ devᵢᵀ + Q dt
    P = symmetrize(weighted_cov(dev, dev, sigma.w_cov)) + dt[:, None, None] * q_matrix
    return tm, qm, em, P


def origin_speed(twist: Tensor, t: Tensor) -> Tensor:
    """(B,) speed (m/s) ``|v_o + ω × t|`` of the object's origin at ``t`` (B,3) under the
    camera-frame twist (B,6) (the cross product written out: it exports to ONNX)."""
    v, w = twist[:, :3], twist[:, 3:]
    c = torch.stack([w[:, 1] * t[:, 2] - w[:, 2] * t[:, 1],
                     w[:, 2] * t[:, 0] - w[:, 0] * t[:, 2],
                     w[:, 0] * t[:, 1] - w[:, 1] * t[:, 0]], dim=-1)
    return torch.linalg.vector_norm(v + c, dim=-1)


def times_bias_transition(M: Tensor, qb: Tensor, db: Tensor) -> Tensor:
    """``M Aᵀ`` for ``M`` (B,9,9) and the transition of a pose filter with a velocity bias,
    ``A = [[R_Δ, 0, db I], [0, R_Δ, 0], [0, 0, I]]`` (``R_Δ`` the rotation of ``qb``
    (B,1,1,4), ``db = s dt`` (B,) s·m/s): each row's first two 3-blocks rotated, ``db`` times
    its bias block added to the first."""
    rotated = quat_rotate(qb, M[..., :6].unflatten(-1, (2, 3))).flatten(-2)
    bias_cols = M[..., 6:]
    return torch.cat([rotated[..., :3] + db[:, None, None] * bias_cols, rotated[..., 3:],
                      bias_cols], dim=-1)
