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

__all__ = ["available", "njit", "warm_up"]

F = TypeVar("F", bound=Callable)


def available() -> bool:
    """Whether numba is installed (:func:`njit` compiles)."""
    return numba is not None


def njit(fn: F) -> F:
    """``fn`` compiled by numba (``nopython``, cached on disk, without the GIL), or ``fn``
    itself where numba is missing."""
    return numba.njit(cache=True, nogil=True)(fn) if numba is not None else fn


def _first_call(values):
    """A trivial compiled function whose first call pays numba's start-up."""
    return values.shape[0]


_first = njit(_first_call)
_warmed = False


def warm_up() -> None:
    """Pay numba's one-time start-up now instead of at the first compiled call.

    The first call of any compiled function in a process loads numba's typing and lowering
    registries (about 0.3 s on 2 cores, measured 2026-11-27); the kernels themselves then
    load from the disk cache in milliseconds each. :class:`evtrack.Tracker` calls this when
    it is made, so that a live stream's first events do not wait for it. Later calls do
    nothing; without numba it does nothing."""
    global _warmed
    if _warmed or numba is None:
        return
    import numpy as np

    _first(np.zeros(1, np.int64))
    _warmed = True
