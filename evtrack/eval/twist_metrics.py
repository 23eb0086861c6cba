"""How well a tracker's twists follow the true motion: scale (gain) and error, by component.

A twist here is ``[v_o (m/s), ω (rad/s)]`` in the camera frame with ``Ṗ = v_o + ω × P`` (the
velocity filter's convention). Between two poses the pose filter integrates the twist, so a
twist that is systematically too small (a *gain* below 1) turns into a pose that lags the object
over the whole pose period, whereas zero-mean noise in it partly averages out.

The gain of an estimate ``x̂`` against the truth ``x`` over samples ``k`` is the least-squares
scale that maps the truth onto the estimate::

    gain = Σ_k x̂_k · x_k / Σ_k x_k · x_k

1: unbiased in scale; 0.5: the estimate carries half of the true motion (the rest lost, e.g.
shrunk toward the filter's prior); it is insensitive to zero-mean noise uncorrelated with the
truth. The gain is reported for the linear and angular parts, for the velocity of the object's
centre ``v_c = v_o + ω × c`` (what moves its image; ``c``: the object's origin in the camera
frame), split into its image-plane (x, y) and depth (z) parts, and for the rotation about the
line of sight to the centre and across it (an object's turn about the line of sight shows in its
image as an in-plane rotation; a turn across it only through perspective and self-occlusion).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

__all__ = ["TwistAgreement", "twist_agreement", "scale_gain"]


def scale_gain(estimate: Tensor, truth: Tensor) -> float:
    """``Σ estimate·truth / Σ truth·truth`` over all entries (NaN when the truth is all zero).

    Args:
        estimate, truth: tensors of one shape, e.g. (N, 3) or (N,).
    """
    denominator = float((truth * truth).sum())
    if denominator <= 0.0:
        return float("nan")
    return float((estimate * truth).sum()) / denominator


@dataclass
class TwistAgreement:
    """Gains (see the module docstring) and root-mean-square errors of estimated twists.

    Attributes:
        samples: samples compared (both twists and the centre finite).
        gain_linear, gain_angular: of ``v_o`` and of ``ω``.
        gain_centre, gain_centre_image, gain_centre_depth: of the centre's velocity ``v_c``,
            of its (x, y) part and of its z part.
        gain_along_sight, gain_across_sight: of ``ω``'s component along the unit line of sight
            ``c/|c|`` and of the rest.
        rmse_linear_m_s, rmse_angular_rad_s, rmse_centre_m_s: RMS of the vector errors.
        mean_speed_rad_s: mean true ``|ω|``.
    """

    samples: int
    gain_linear: float
    gain_angular: float
    gain_centre: float
    gain_centre_image: float
    gain_centre_depth: float
    gain_along_sight: float
    gain_across_sight: float
    rmse_linear_m_s: float
    rmse_angular_rad_s: float
    rmse_centre_m_s: float
    mean_speed_rad_s: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def twist_agreement(estimate: Tensor, truth: Tensor, centres: Tensor) -> TwistAgreement:
    """Compare estimated twists with true ones at the same times.

    Args:
        estimate: (N, 6) estimated ``[v_o, ω]`` (m/s, rad/s), camera frame.
        truth: (N, 6) true twists, same convention.
        centres: (N, 3) the object's origin in the camera frame (m), e.g. the true poses'
            translations.

    Returns:
        the agreement over the rows where all three are finite (``samples`` 0 and NaN gains
        when there is none).

    Raises:
        ValueError: shapes that do not match.

    Example:
        >>> truth = torch.tensor([[0.1, 0.0, 0.0, 0.0, 0.0, 2.0], [0.0, 0.1, 0.0, 1.0, 0.0, 0.0]])
        >>> centres = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5]])
        >>> twist_agreement(0.5 * truth, truth, centres).gain_angular
        0.5
    """
    estimate = torch.as_tensor(estimate, dtype=torch.float64)
    truth = torch.as_tensor(truth, dtype=torch.float64)
    centres = torch.as_tensor(centres, dtype=torch.float64)
    n = truth.shape[0] if truth.ndim == 2 else -1
    if estimate.shape != (n, 6) or truth.shape != (n, 6) or centres.shape != (n, 3):
        raise ValueError(f"twist_agreement: estimate and truth must be (N, 6) and centres "
                         f"(N, 3), got {tuple(estimate.shape)}, {tuple(truth.shape)}, "
                         f"{tuple(centres.shape)}")
    ok = (torch.isfinite(estimate).all(1) & torch.isfinite(truth).all(1)
          & torch.isfinite(centres).all(1))
    est, tru, c = estimate[ok], truth[ok], centres[ok]
    v_est, w_est = est[:, :3], est[:, 3:]
    v_tru, w_tru = tru[:, :3], tru[:, 3:]
    vc_est = v_est + torch.linalg.cross(w_est, c)
    vc_tru = v_tru + torch.linalg.cross(w_tru, c)
    sight = c / torch.linalg.vector_norm(c, dim=1, keepdim=True).clamp(min=1e-12)
    along_est = (w_est * sight).sum(1)
    along_tru = (w_tru * sight).sum(1)
    across_est = w_est - along_est[:, None] * sight
    across_tru = w_tru - along_tru[:, None] * sight

    def rmse(a: Tensor, b: Tensor) -> float:
        return float(((a - b) ** 2).sum(1).mean().sqrt()) if len(a) else float("nan")

    return TwistAgreement(
        samples=int(ok.sum()),
        gain_linear=scale_gain(v_est, v_tru),
        gain_angular=scale_gain(w_est, w_tru),
        gain_centre=scale_gain(vc_est, vc_tru),
        gain_centre_image=scale_gain(vc_est[:, :2], vc_tru[:, :2]),
        gain_centre_depth=scale_gain(vc_est[:, 2], vc_tru[:, 2]),
        gain_along_sight=scale_gain(along_est, along_tru),
        gain_across_sight=scale_gain(across_est, across_tru),
        rmse_linear_m_s=rmse(v_est, v_tru),
        rmse_angular_rad_s=rmse(w_est, w_tru),
        rmse_centre_m_s=rmse(vc_est, vc_tru),
        mean_speed_rad_s=(float(torch.linalg.vector_norm(w_tru, dim=1).mean()) if len(w_tru)
                          else float("nan")),
    )
