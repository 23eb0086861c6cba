"""Laplacian weights against the paper's formula evaluated directly (numpy, per track)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.filters.linalg import portable_linalg
from evtrack.filters.weighting import laplacian_weights, masked_lower_median


def _reference(
    r: np.ndarray, b: float | None, b_min: float, floor: float, prev: np.ndarray | None = None
) -> np.ndarray:
    """L_k = max(exp(-|r_k - M|/b)/(2b), floor), relative to the largest value L can take."""
    M = np.sort(r)[(len(r) - 1) // 2]  # lower median
    dev = np.abs(r - M)
    if b is None:
        b = dev.mean() if prev is None else (prev * dev).sum() / prev.sum()
        b = max(b, b_min)
    L = np.maximum(np.exp(-dev / b) / (2 * b), floor)
    return L / max(1 / (2 * b), floor)


def _batch(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    r = torch.randn(5, 41, generator=g, dtype=torch.float64) * 30
    r[:, :6] += 800  # outliers
    valid = torch.rand(5, 41, generator=g) < 0.8
    valid[4] = False  # a track without any valid row
    valid[3, :] = False
    valid[3, 7] = True  # a track with a single valid row
    return r, valid


@pytest.mark.parametrize("scale", [None, 25.0, 1e7])
def test_matches_paper_formula(scale: float | None) -> None:
    r, valid = _batch(0)
    rho = laplacian_weights(r, valid, scale, scale_min=1.0, floor=1e-6)
    for i in range(5):
        v = valid[i].numpy()
        assert torch.all(rho[i][~valid[i]] == 0)
        if v.any():
            ref = _reference(r[i].numpy()[v], scale, 1.0, 1e-6)
            np.testing.assert_allclose(rho[i].numpy()[v], ref, rtol=1e-12, atol=0)


def test_reweighting_uses_previous_weights_for_the_scale() -> None:
    r, valid = _batch(1)
    first = laplacian_weights(r, valid, None, 1.0, 1e-6)
    second = laplacian_weights(r, valid, None, 1.0, 1e-6, previous=first)
    for i in range(3):
        v = valid[i].numpy()
        ref = _reference(r[i].numpy()[v], None, 1.0, 1e-6, prev=first[i].numpy()[v])
        np.testing.assert_allclose(second[i].numpy()[v], ref, rtol=1e-12)
    # Outliers inflate the mean deviation; the reweighted scale excludes them: they lose weight.
    assert (second[:3, :6][valid[:3, :6]] < first[:3, :6][valid[:3, :6]]).all()


def test_floor_and_bounds() -> None:
    r = torch.tensor([[0.0, 1.0, 2.0, 1e4]], dtype=torch.float64)
    rho = laplacian_weights(r, torch.ones_like(r, dtype=torch.bool), scale=1.0, floor=1e-6)
    assert rho[0, 1] == 1.0  # the median
    assert rho[0, 3] == pytest.approx(2e-6)  # floored: 1e-6 / (1/2)
    assert ((rho > 0) & (rho <= 1)).all()


def test_median_is_lower_median_and_portable_path_agrees() -> None:
    r, valid = _batch(2)
    med, count = masked_lower_median(r, valid)
    with portable_linalg():
        med_p, count_p = masked_lower_median(r, valid)
    assert torch.equal(med, med_p) and torch.equal(count, count_p)
    for i in range(5):
        vals = r[i][valid[i]]
        expected = vals.sort().values[(len(vals) - 1) // 2] if len(vals) else torch.tensor(0.0)
        assert med[i] == expected
