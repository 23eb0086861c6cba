"""numba for the flow's compiled kernels: whether it is there, the kernels' decorator, the
parallel range, an allocation helper and the thread count shared with torch.

numba is optional: without it :func:`kernel` returns functions unchanged (plain Python),
``prange`` is ``range`` and :func:`available` says False, so that the flow picks its tensor
backend (:func:`evtrack.flow.backends.resolve`). The kernels are cached on disk (numba's
``cache=True``: ``__pycache__`` beside their module, or ``NUMBA_CACHE_DIR``) and release the
GIL; the first use compiles them (a few seconds), later processes load them in a fraction of
a second.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import numpy as np
import torch

try:  # numba is optional: without it the torch backend runs everywhere
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

__all__ = ["available", "kernel", "prange", "filled", "torch_thread_count", "thread_limit", "numba"]

F = TypeVar("F", bound=Callable[..., Any])

prange = numba.prange if numba is not None else range
"""numba's parallel range inside ``kernel(parallel=True)`` functions (``range`` without
numba)."""


def available() -> bool:
    """Whether numba is installed (the compiled kernels can run)."""
    return numba is not None


def kernel(**options: Any) -> Callable[[F], F]:
    """Decorator: the function compiled by numba (``nopython``, cached on disk, without the
    GIL, plus ``options`` such as ``parallel=True`` or ``inline="always"``), or the function
    itself where numba is missing."""
    def wrap(fn: F) -> F:
        return numba.njit(cache=True, nogil=True, **options)(fn) if numba is not None else fn
    return wrap


@kernel()
def filled(shape, value, dtype):
    """``np.full(shape, value, dtype)`` compiled on its own. Written inside a
    ``parallel=True`` kernel, an array constructor (``np.zeros``, ``np.full``, a copy) becomes
    a parallel loop of its own, one thread-pool launch per array, which costs more than
    filling the few thousand entries of a tracker's call; through this helper it stays a
    plain loop."""
    return np.full(shape, value, dtype)


@contextmanager
def torch_thread_count() -> Iterator[None]:
    """Run numba's parallel kernels inside on as many threads as torch may use, and leave
    torch's count as it was: numba's OpenMP layer resets the process's OpenMP thread count
    (torch's) when it starts."""
    threads = torch.get_num_threads()
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


def thread_limit() -> int:
    """Most threads numba's parallel kernels may use now: torch's count, capped by numba's
    pool (1 without numba)."""
    if numba is None:
        return 1
    return min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
