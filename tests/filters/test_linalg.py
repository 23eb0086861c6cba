"""The unrolled (ONNX-exportable) SPD kernels against LAPACK."""

from __future__ import annotations

import pytest
import torch

from evtrack.filters.linalg import cholesky, portable_linalg, spd_inverse, symmetrize, use_portable


def _spd(n: int, batch: int, cond: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(batch, n, n, generator=g, dtype=torch.float64))
    eig = torch.logspace(0, torch.log10(torch.tensor(cond)).item(), n, dtype=torch.float64)
    return symmetrize(Q @ torch.diag_embed(eig) @ Q.transpose(-1, -2))


@pytest.mark.parametrize("n", [6, 12])
def test_unrolled_equals_lapack(n: int) -> None:
    A = _spd(n, 20, 1e6, n)
    with portable_linalg():
        assert use_portable()
        L_p, inv_p = cholesky(A), spd_inverse(A)
    assert not use_portable()
    L = torch.linalg.cholesky(A)
    assert torch.allclose(L_p, L, rtol=0, atol=1e-11 * L.abs().max())
    assert torch.allclose(L_p @ L_p.transpose(-1, -2), A, rtol=0, atol=1e-14 * A.abs().max())
    inv = torch.linalg.inv(A)
    assert torch.allclose(inv_p, inv, rtol=1e-9, atol=1e-12 * inv.abs().max())
    assert torch.allclose(spd_inverse(A), inv, rtol=1e-9, atol=1e-12 * inv.abs().max())
    assert torch.equal(inv_p, inv_p.transpose(-1, -2))  # exactly symmetric


def test_lower_triangular_and_float32() -> None:
    A = _spd(6, 4, 1e3, 7).float()
    with portable_linalg():
        L = cholesky(A)
    assert torch.equal(L, torch.tril(L))
    assert torch.allclose(L @ L.transpose(-1, -2), A, rtol=1e-5, atol=1e-5)
