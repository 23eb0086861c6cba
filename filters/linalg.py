"""Small symmetric positive-definite (SPD) matrix kernels with an ONNX-exportable form.

ONNX has no Cholesky, matrix inverse or solve operator, so while a model is being exported
(:func:`torch.onnx.export`, :func:`torch.export.export`) these functions switch to an unrolled
form made of elementwise ops and matmuls (the matrix size is static: 6 or 12 here). In eager
mode they call LAPACK through ``torch.linalg``. Both forms are pinned to each other in
``tests/filters/test_linalg.py``; :func:`portable_linalg` forces the unrolled form.

No function branches on tensor values: a matrix that is not SPD gives NaN or garbage, never an
exception (the filters keep their covariances symmetric and positive definite).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import Tensor

__all__ = ["cholesky", "spd_inverse", "spd_solve", "symmetrize", "portable_linalg", "use_portable"]

_FORCE_PORTABLE = [False]


@contextmanager
def portable_linalg(enabled: bool = True) -> Iterator[None]:
    """Force (or forbid) the unrolled, ONNX-exportable kernels inside the ``with`` block."""
    previous = _FORCE_PORTABLE[0]
    _FORCE_PORTABLE[0] = enabled
    try:
        yield
    finally:
        _FORCE_PORTABLE[0] = previous


def use_portable() -> bool:
    """True while exporting or tracing (``torch.onnx.export`` with either exporter,
    ``torch.export``, ``torch.jit.trace``) or inside :func:`portable_linalg`."""
    return (
        _FORCE_PORTABLE[0]
        or torch.compiler.is_exporting()
        or torch._C._get_tracing_state() is not None
    )


def symmetrize(A: Tensor) -> Tensor:
    """``(A + Aᵀ) / 2`` over the last two dimensions."""
    return 0.5 * (A + A.transpose(-1, -2))


def cholesky(A: Tensor) -> Tensor:
    """Lower Cholesky factor ``L`` with ``L Lᵀ = A``; A (*,n,n) SPD -> (*,n,n)."""
    if use_portable():
        return _cholesky_unrolled(A)
    return torch.linalg.cholesky_ex(A).L


def spd_inverse(A: Tensor) -> Tensor:
    """Inverse of SPD matrices (*,n,n) -> (*,n,n), exactly symmetric."""
    if use_portable():
        Linv = _tril_inverse_unrolled(_cholesky_unrolled(A))
        return symmetrize(Linv.transpose(-1, -2) @ Linv)  # A⁻¹ = L⁻ᵀ L⁻¹
    return torch.cholesky_inverse(torch.linalg.cholesky_ex(A).L)  # exactly symmetric


def spd_solve(A: Tensor, B: Tensor) -> Tensor:
    """``A⁻¹ B`` for SPD ``A`` (*,n,n) and ``B`` (*,n,k) -> (*,n,k)."""
    if use_portable():
        return spd_inverse(A) @ B
    return torch.linalg.solve_ex(A, B).result


def _cholesky_unrolled(A: Tensor) -> Tensor:
    """Column-by-column Cholesky–Banachiewicz, unrolled over the static size n."""
    n = A.shape[-1]
    cols: list[Tensor] = []
    for j in range(n):
        s = A[..., :, j]
        if cols:
            Lc = torch.stack(cols, dim=-1)  # (*, n, j)
            s = s - (Lc @ Lc[..., j, :].unsqueeze(-1)).squeeze(-1)
        d = torch.sqrt(s[..., j : j + 1])
        col = torch.cat([torch.zeros_like(s[..., :j]), d, s[..., j + 1 :] / d], dim=-1)
        cols.append(col)
    return torch.stack(cols, dim=-1)


def _tril_inverse_unrolled(L: Tensor) -> Tensor:
    """Inverse of lower-triangular matrices by forward substitution, row by row."""
    n = L.shape[-1]
    eye = torch.eye(n, dtype=L.dtype, device=L.device)
    rows: list[Tensor] = []
    for i in range(n):
        r = eye[i].expand_as(L[..., i, :])
        if rows:
            X = torch.stack(rows, dim=-2)  # (*, i, n)
            r = r - (L[..., i : i + 1, :i] @ X).squeeze(-2)
        rows.append(r / L[..., i, i : i + 1])
    return torch.stack(rows, dim=-2)
