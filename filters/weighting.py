"""Laplacian weighting of measurement residuals around their median (paper III-B.5).

For the valid residuals ``r_j`` of one track, with ``M`` their median (the lower median for an
even count) and ``b`` the Laplacian scale::

    L_j = max(exp(-|r_j - M| / b) / (2b), floor)           (the paper's weight)
    ρ_j = L_j / L_max,   L_max = max(1/(2b), floor)        (1 at the median, in (0, 1])
    R_j = R / ρ_j                                          (the measurement noise of row j)

so a residual at the median keeps the nominal noise ``R`` and a far one has its variance
inflated by up to ``L_max / floor``: in the information form the row's information is scaled
by ``ρ_j``. ``b`` defaults to the mean absolute deviation around the median, the
maximum-likelihood scale of a Laplace distribution located at ``M``. When the weights are
re-estimated (iteratively reweighted), the deviations are averaged with the previous pass's
weights, ``b = Σ ρ_j |r_j − M| / Σ ρ_j``: the EM update of the scale of the inlier component,
which outliers no longer inflate.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evtrack.filters.linalg import use_portable

__all__ = ["masked_lower_median", "laplacian_weights"]


def masked_lower_median(values: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Lower median of the valid entries along the last dimension.

    Args:
        values: (*, K) finite where ``valid``; valid: (*, K) bool.

    Returns:
        ``(median (*), count (*) int64)``; the median is 0 where no entry is valid.
    """
    count = valid.sum(-1)
    if use_portable():  # ONNX has no NaN-aware median: sort with +inf padding, pick index k
        keyed = torch.where(valid, values, torch.inf)
        ordered = torch.sort(keyed, dim=-1).values
        k = torch.clamp((count - 1) // 2, min=0)
        med = torch.gather(ordered, -1, k.unsqueeze(-1)).squeeze(-1)
    else:  # the same lower median in one kernel
        med = torch.nanmedian(torch.where(valid, values, torch.nan), dim=-1).values
    return torch.where(count > 0, med, 0.0), count


def laplacian_weights(
    residuals: Tensor,
    valid: Tensor,
    scale: float | Tensor | None = None,
    scale_min: float | Tensor = 1.0,
    floor: float | Tensor = 1e-6,
    previous: Tensor | None = None,
) -> Tensor:
    """Relative weights ``ρ_j`` in (0, 1] of residual rows (0 on invalid rows).

    Args:
        residuals: (*, K) residuals (px/s); entries where ``valid`` is False are ignored.
        valid: (*, K) bool.
        scale: the Laplacian scale ``b`` (px/s); ``None``: per track, the mean absolute
            deviation around the median (weighted by ``previous`` if given), bounded below by
            ``scale_min``.
        scale_min: px/s, lower bound of an estimated scale.
        floor: the floor on the Laplacian density ``L_j`` (1/(px/s)).
            (``scale``, ``scale_min`` and ``floor`` may be 0-d tensors: exported graphs keep
            tensors at full precision, Python floats as float32 constants.)
        previous: (*, K) weights of a previous pass, or ``None`` on the first pass.

    Returns:
        (*, K) weights; multiply a row's information (divide its noise variance) by them.
    """
    med = _lower_median_nan(residuals, valid)  # NaN for a track without valid rows
    dev = (residuals - med).abs()
    if scale is None:
        if previous is None:
            total = torch.where(valid, dev, 0.0).sum(-1, keepdim=True)
            b = total / valid.sum(-1, keepdim=True).clamp(min=1)
        else:  # previous is 0 on invalid rows
            total = (previous * dev).sum(-1, keepdim=True)
            b = total / previous.sum(-1, keepdim=True).clamp(min=torch.finfo(dev.dtype).tiny)
        b = torch.clamp(b, min=scale_min)
    else:
        b = torch.zeros_like(dev[..., :1]) + scale
    # ρ = max(e/(2b), floor) / max(1/(2b), floor) with e = exp(-|r - M|/b), i.e.
    # ρ = max(e, min(2b·floor, 1)): the same value in three ops.
    rho = torch.maximum(torch.exp(dev / -b), (2.0 * b * floor).clamp(max=1.0))
    return torch.where(valid, rho, 0.0)  # also drops the NaN of tracks without valid rows


def _lower_median_nan(values: Tensor, valid: Tensor) -> Tensor:
    """(*, K) -> (*, 1) lower median of the valid entries, NaN where there is none."""
    if use_portable():
        med, count = masked_lower_median(values, valid)
        return torch.where(count > 0, med, torch.nan).unsqueeze(-1)
    return torch.nanmedian(torch.where(valid, values, torch.nan), dim=-1, keepdim=True).values
