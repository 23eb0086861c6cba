"""Unscented-transform machinery on the pose manifold ``R³ × S³ (× Rᵏ)``, batched.

A state is a pose ``(t, q)`` plus ``k`` Euclidean entries ``e`` (the twist for the
constant-velocity filter); its covariance lives in the tangent ``[δt, δθ, δe]`` of dimension
``n = 6 + k`` with left (camera-frame) rotation perturbations ``q = exp(δθ) ⊗ q̄``
(:mod:`lie`). Sigma points are ``x̄ ⊞ (±γ Lᵢ)`` with ``L Lᵀ = P`` (van der Merwe's scaled
points). The mean of sigma quaternions is a weighted Karcher mean: it solves
``Σ Wᵢ log(qᵢ ⊗ q̄⁻¹) = 0``, where ``log`` takes the shortest rotation, so ``q`` and ``-q``
average alike (the double cover). Deviations are taken in the same chart, so means and
covariances agree with ``⊞``/``⊟``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from evtrack.filters.lie import quat_conj, quat_exp, quat_log, quat_mul
from evtrack.filters.linalg import cholesky

__all__ = [
    "SigmaWeights",
    "UnscentedParams",
    "merwe_weights",
    "quat_mean",
    "sigma_offsets",
    "weighted_cov",
]


@dataclass(frozen=True)
class SigmaWeights:
    """Weights of ``2n + 1`` scaled sigma points.

    Attributes:
        mean: (2n+1,) weights of the mean (sum to 1).
        cov: (2n+1,) weights of the covariance.
        gamma: spread: the points sit at ``±gamma`` standard deviations.
    """

    mean: tuple[float, ...]
    cov: tuple[float, ...]
    gamma: float


class UnscentedParams(NamedTuple):
    """A filter's sigma-point parameters as tensors of its dtype (exported graphs keep them at
    full precision).

    Attributes:
        gamma: () the spread of the points, in standard deviations.
        w_mean: (2n+1,) weights of the mean. w_cov: (2n+1,) weights of the covariance.
        mean_iterations: Gauss–Newton steps of the quaternion mean (:func:`quat_mean`).
    """

    gamma: Tensor
    w_mean: Tensor
    w_cov: Tensor
    mean_iterations: int


def merwe_weights(n: int, alpha: float, beta: float, kappa: float) -> SigmaWeights:
    """Van der Merwe's scaled sigma-point weights (as filterpy's ``MerweScaledSigmaPoints``).

    ``λ = α² (n + κ) − n``; ``Wm₀ = λ/(n+λ)``, ``Wc₀ = Wm₀ + 1 − α² + β``,
    ``Wᵢ = 1/(2(n+λ))``; ``γ = √(n+λ)``.
    """
    lam = alpha**2 * (n + kappa) - n
    if not n + lam > 0:
        raise ValueError(f"sigma points need n + lambda > 0, got n={n}, lambda={lam}")
    w = 0.5 / (n + lam)
    m0 = lam / (n + lam)
    return SigmaWeights(
        (m0,) + (w,) * (2 * n), (m0 + 1 - alpha**2 + beta,) + (w,) * (2 * n), (n + lam) ** 0.5
    )


def sigma_offsets(cov: Tensor, gamma: float | Tensor) -> Tensor:
    """Tangent offsets of the sigma points: ``0, +γ Lᵢ, −γ Lᵢ`` for ``L Lᵀ = P``.

    Args:
        cov: (B, n, n) SPD.

    Returns:
        (B, 2n+1, n), row ``i`` being the offset of point ``i``.
    """
    cols = (gamma * cholesky(cov)).transpose(-1, -2)  # row i = column i of γL
    return torch.cat([torch.zeros_like(cols[:, :1]), cols, -cols], dim=1)


def quat_mean(q: Tensor, weights: Tensor, init: Tensor, iterations: int) -> tuple[Tensor, Tensor]:
    """Weighted Karcher mean of unit quaternions and the deviations from it.

    Args:
        q: (B, S, 4) unit quaternions (either sign).
        weights: (S,) summing to 1 (may be zero or negative at the centre point).
        init: (B, 4) starting point (e.g. the propagated centre point).
        iterations: Gauss–Newton steps ``q̄ ← exp(Σ Wᵢ log(qᵢ ⊗ q̄⁻¹)) ⊗ q̄``.

    Returns:
        ``(q̄ (B,4) unit, deviations (B,S,3) = log(qᵢ ⊗ q̄⁻¹))``.
    """
    qm = init
    for _ in range(iterations):
        dev = quat_log(quat_mul(q, quat_conj(qm).unsqueeze(1)))
        qm = quat_mul(quat_exp((weights.unsqueeze(-1) * dev).sum(1)), qm)
    qm = qm / torch.linalg.vector_norm(qm, dim=-1, keepdim=True)
    return qm, quat_log(quat_mul(q, quat_conj(qm).unsqueeze(1)))


def weighted_cov(a: Tensor, b: Tensor, weights: Tensor) -> Tensor:
    """``Σᵢ Wᵢ aᵢ bᵢᵀ`` for deviations a (B,S,n), b (B,S,m) and weights (S,) -> (B,n,m)."""
    return (a * weights.unsqueeze(-1)).transpose(-1, -2) @ b
