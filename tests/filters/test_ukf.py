"""Sigma points and the quaternion mean against filterpy and their defining properties."""

from __future__ import annotations

import numpy as np
import torch
from filterpy.kalman import MerweScaledSigmaPoints

from evtrack.filters.lie import quat_conj, quat_exp, quat_log, quat_mul
from evtrack.filters.ukf import merwe_weights, quat_mean, sigma_offsets, weighted_cov


def test_weights_and_points_match_filterpy() -> None:
    for n, (alpha, beta, kappa) in [(6, (1.0, 2.0, 0.0)), (12, (0.5, 2.0, 1.0))]:
        ref = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
        w = merwe_weights(n, alpha, beta, kappa)
        np.testing.assert_allclose(w.mean, ref.Wm, rtol=1e-14)
        np.testing.assert_allclose(w.cov, ref.Wc, rtol=1e-14)
        g = torch.Generator().manual_seed(n)
        a = torch.randn(n, n, generator=g, dtype=torch.float64)
        P = a @ a.T + torch.eye(n, dtype=torch.float64)
        x = torch.randn(n, generator=g, dtype=torch.float64)
        pts = x + sigma_offsets(P[None], w.gamma)[0]
        np.testing.assert_allclose(pts.numpy(), ref.sigma_points(x.numpy(), P.numpy()), atol=1e-12)
        # and they reproduce the mean and covariance
        offs = pts - x
        torch.testing.assert_close(
            weighted_cov(offs[None], offs[None], torch.tensor(w.cov, dtype=torch.float64))[0], P
        )


def test_quaternion_mean_is_stationary_and_sign_blind() -> None:
    g = torch.Generator().manual_seed(0)
    B, S = 4, 25
    center = quat_exp(torch.randn(B, 3, generator=g, dtype=torch.float64))
    spread = 0.15 * torch.randn(B, S, 3, generator=g, dtype=torch.float64)
    q = quat_mul(quat_exp(spread), center[:, None])
    w = torch.rand(S, generator=g, dtype=torch.float64)
    w = w / w.sum()
    mean, dev = quat_mean(q, w, q[:, 0], iterations=10)
    # The weighted Karcher mean: deviations average to zero.
    assert (w[:, None] * dev).sum(1).abs().max() < 1e-12
    assert torch.allclose(mean.norm(dim=-1), torch.ones(B, dtype=torch.float64), atol=1e-15)
    signs = torch.where(torch.rand(B, S, 1, generator=g) < 0.5, -1.0, 1.0).to(torch.float64)
    mean_flipped, dev_flipped = quat_mean(q * signs, w, -q[:, 0], iterations=10)
    same = torch.minimum((mean - mean_flipped).abs().amax(-1), (mean + mean_flipped).abs().amax(-1))
    assert same.max() < 1e-14
    torch.testing.assert_close(dev_flipped, dev, rtol=0, atol=1e-13)
    # The deviations are the chart of each point around the mean.
    torch.testing.assert_close(dev, quat_log(quat_mul(q, quat_conj(mean)[:, None])))
