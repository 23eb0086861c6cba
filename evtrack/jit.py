"""Optional numba compilation of small single-threaded kernels.

numba is a dependency, but the code runs without it: :func:`njit` then returns the function
unchanged (plain Python, same results) and :func:`available` says False, so that callers with
a faster NumPy form can take it instead. Compiled functions are cached on disk (numba's
``cache=True``: ``__pycache__`` beside the module, or ``NUMBA_CACHE_DIR``) and release the
GIL. The flow's parallel kernels have their own options (:mod:`evtrack.flow.compiled`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

try:
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

__all__ = ["available", "njit"]

F = TypeVar("F", bound=Callable)


def available() -> bool:
    """Whether numba is installed (:func:`njit` compiles)."""
    return numba is not None


def njit(fn: F) -> F:
    """``fn`` compiled by numba (``nopython``, cached on disk, without the GIL), or ``fn``
    itself where numba is missing."""
    return numba.njit(cache=True, nogil=True)(fn) if numba is not None else fn
