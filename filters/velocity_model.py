"""The velocity filter's measurement model and weighted information-form update, batched in
torch: the specification of :meth:`VelocityKF.update_state` (see :mod:`velocity_kf` for the
model).

Each RoI flow ``F`` (px/s) is written in its flow-aligned frame ``n = F/|F|``, ``n⊥``: an along
row measuring ``nᵀ J V = |F|`` and, for a full flow, an across row ``n⊥ᵀ J V = 0`` (``J``: the
interaction matrix, :mod:`interaction`). The rows are weighted by
:func:`weighting.laplacian_weights` and fused in information form. No function branches on
tensor values, so both export to ONNX.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evtrack.filters.config import VelocityKFConfig
from evtrack.filters.linalg import spd_inverse
from evtrack.filters.weighting import laplacian_weights

__all__ = ["measurement_rows", "weighted_update"]


def measurement_rows(
    uv: Tensor,
    depth: Tensor,
    flow: Tensor,
    normal_only: Tensor,
    mask: Tensor,
    focal: Tensor,
    principal: Tensor,
    normal_flow: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The measurement rows of B tracks' RoIs.

    A row ``(a, b)·J`` of the interaction matrix, with ``a = e_u fx``, ``b = e_v fy`` for a unit
    direction ``e`` and ``p = a x + b y``, is
    ``[a/Z, b/Z, −p/Z, −(y p + b), a + x p, b x − a y]``: a few elementwise ops per RoI, for the
    along (``e = n``) and across (``e = n⊥``) rows at once.

    Args:
        uv: (B, N, 2) ideal pinhole px. depth: (B, N) m. flow: (B, N, 2) px/s.
        normal_only: (B, N) bool. mask: (B, N) bool, False on padding.
        focal: (2,) ``[fx, fy]`` px. principal: (2,) ``[cx, cy]`` px.
        normal_flow: the normal-flow constraint (``VelocityKFConfig.normal_flow``): a
            normal-only RoI keeps its along row only, and one with a zero flow is skipped.

    Returns:
        Rows ``H`` (B, 2N, 6), values ``z`` (B, 2N) px/s, row validity (B, 2N) bool, and the
        counts (B, 2) of RoIs skipped for a bad depth and for a bad flow or pixel.
    """
    B, N = depth.shape
    depth_ok = mask & (depth > 0) & (depth < torch.inf)  # False for NaN too
    both = uv + flow
    finite = torch.isfinite(both[..., 0] + both[..., 1])
    flow0 = torch.where(finite.unsqueeze(-1), flow, 0.0)
    fu, fv = flow0.unbind(-1)
    mag = torch.sqrt(fu * fu + fv * fv)
    moving = mag > 0
    if normal_flow:  # a zero normal flow has no direction
        valid = depth_ok & finite & (moving | ~normal_only)
    else:
        valid = depth_ok & finite
    counts = torch.stack([mask, depth_ok, valid], dim=-1).sum(-2)
    skipped = counts[:, :2] - counts[:, 1:]

    xy = (torch.where(valid.unsqueeze(-1), uv, principal) - principal) / focal
    x, y = xy.unsqueeze(-2).unbind(-1)  # (B,N,1) each
    iz = (1.0 / torch.where(valid, depth, 1.0)).unsqueeze(-1)
    # Flow-aligned frame: along n = F/|F|, across n⊥; the image axes for a zero full flow.
    inv_mag = 1.0 / torch.where(moving, mag, 1.0)
    nx = torch.where(moving, fu * inv_mag, 1.0)
    ny = fv * inv_mag
    fx, fy = focal.unbind()
    a = torch.stack([nx, -ny], dim=-1) * fx  # (B,N,2): along, across
    b = torch.stack([ny, nx], dim=-1) * fy
    p = a * x + b * y
    H = torch.stack([a * iz, b * iz, -(p * iz), -(y * p + b), a + x * p, b * x - a * y], -1)
    z = torch.stack([torch.where(valid, mag, 0.0), torch.zeros_like(mag)], dim=-1)
    across_ok = valid & ~normal_only if normal_flow else valid
    rows_ok = torch.stack([valid, across_ok], dim=-1)
    return H.reshape(B, 2 * N, 6), z.reshape(B, 2 * N), rows_ok.reshape(B, 2 * N), skipped


def weighted_update(
    cfg: VelocityKFConfig,
    consts: Tensor,
    twist: Tensor,
    cov: Tensor,
    reference: Tensor,
    H: Tensor,
    z: Tensor,
    rows_ok: Tensor,
    normal_only: Tensor,
) -> tuple[Tensor, Tensor]:
    """The Laplacian-weighted information-form update over ``cfg.weighting_iterations``
    passes: ``Λ = P⁻¹ + Hᵀ W H``, ``P⁺ = Λ⁻¹``, ``V⁺ = V + P⁺ Hᵀ W (z − H V)``.

    Args:
        cfg: the filter's config. consts: (6,) the filter's ``consts`` buffer
            ``[ln(alpha)/alpha_dt, 1/σ_F², b or 0, b_min, floor, 1/σ_N²]``.
        twist: (B, 6) the prior twist. cov: (B, 6, 6) its covariance.
        reference: (B, 6) the twist the first weighting pass compares flows with (used when
            ``weighting_reference == "previous"``).
        H, z, rows_ok: the rows of :func:`measurement_rows` (B, 2N, 6), (B, 2N), (B, 2N).
        normal_only: (B, N) bool, True where a RoI's flow is normal-only.

    Returns:
        The posterior twist (B, 6) and covariance (B, 6, 6), of ``twist``'s dtype. A float32
        filter sums the information and does the 6x6 algebra in float64.
    """
    out_dtype = twist.dtype
    if out_dtype != torch.float64:
        # Information sums over hundreds of RoIs and the 6x6 algebra lose about four
        # digits to the conditioning in float32; in float64 they cost nothing extra.
        H, z, twist, cov, reference = (x.double() for x in (H, z, twist, cov, reference))
    consts = consts if out_dtype == torch.float64 else consts.double()
    _, flow_info, scale, scale_min, floor, normal_info = consts.unbind()
    if cfg.normal_flow and cfg.normal_flow_std is not None:
        # the along row of a normal-only RoI has its own noise; the across rows R_F
        along_normal = torch.stack([normal_only, torch.zeros_like(normal_only)], dim=-1)
        flow_info = torch.where(along_normal.reshape(z.shape), normal_info, flow_info)
    HT = H.transpose(-1, -2)
    innovation = z - (H @ twist.unsqueeze(-1)).squeeze(-1)  # (B, 2N)
    innovation_col = innovation.unsqueeze(-1)
    prior_info = spd_inverse(cov)
    if cfg.weighting and cfg.weighting_reference == "previous":
        residual = z - (H @ reference.unsqueeze(-1)).squeeze(-1)
    else:
        residual = innovation
    passes = cfg.weighting_iterations if cfg.weighting else 1
    rho: Tensor | None = None
    post_twist, post_cov = twist, cov
    for i in range(passes):
        if cfg.weighting:
            rho = laplacian_weights(
                residual,
                rows_ok,
                None if cfg.laplace_scale is None else scale,
                scale_min,
                floor,
                rho,
            )
            info = rho * flow_info
        else:
            info = rows_ok * flow_info
        HTw = HT * info.unsqueeze(-2)  # Hᵀ W, (B, 6, 2N)
        # Λ = P⁻¹ + Hᵀ W H;  P⁺ = Λ⁻¹;  V⁺ = V + P⁺ Hᵀ W (z − H V)
        post_cov = spd_inverse(torch.baddbmm(prior_info, HTw, H))
        post_twist = torch.baddbmm(twist.unsqueeze(-1), post_cov, HTw @ innovation_col).squeeze(
            -1
        )
        if i + 1 < passes:
            residual = z - (H @ post_twist.unsqueeze(-1)).squeeze(-1)
    return post_twist.to(out_dtype), post_cov.to(out_dtype)
