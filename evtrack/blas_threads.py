"""numpy's BLAS threads while the tracker runs: one, so that idle BLAS workers do not spin.

numpy's wheels bring OpenBLAS, which starts its worker threads when numpy is imported. After
a BLAS call large enough to be split across them (a product with a few thousand rows: the
mesh's vertices, a depth patch), the workers busy-wait for the next call for a while before
they sleep. The tracker makes such calls every few milliseconds, so one worker spun almost
all the time (82 % of samples running, on a 2 s ``faster`` sequence) and took a core from the
flow's kernels and the filters. Measured on the cracker box ``faster`` sequence (2 cores, 2
torch threads, full method): 38.7 s of processing with OpenBLAS's own threads, 30.3 s with
one BLAS thread; with the flow's strips searched in parallel 35.3 s against 22.3 s (the
second strip's thread had no free core before).

:class:`BlasThreads` sets the limit with threadpoolctl (whatever the import order, for
OpenBLAS, MKL and BLIS alike) and puts the libraries' own settings back on exit. It is
re-entrant per thread: nested uses (``Tracker.track`` calling ``push_events``) cost nothing.

Trackers working at the same time in several threads of one process: the libraries' limits
are process-wide for some builds and per thread for others, and each use restores what it
found when it started, so overlapping uses can lift each other's limit early or leave the
limit in place after the last one ends. Set ``blas_threads: 0`` for such trackers and limit
BLAS once around them yourself (``threadpoolctl.threadpool_limits(1, "blas")``).
"""

from __future__ import annotations

import threading
from types import TracebackType

__all__ = ["BlasThreads"]

_controller = None
_controller_lock = threading.Lock()


def _thread_pools():
    """The process's threadpoolctl controller, made at first use (it scans the loaded
    libraries: numpy's BLAS is loaded by then, evtrack imports numpy)."""
    global _controller
    with _controller_lock:
        if _controller is None:
            from threadpoolctl import ThreadpoolController

            _controller = ThreadpoolController()
        return _controller


class BlasThreads:
    """Context manager: at most ``threads`` BLAS threads inside, the previous limits after.

    Args:
        threads: the limit (>= 1); 0 leaves the libraries' settings alone.

    Example:
        >>> import numpy as np
        >>> with BlasThreads(1):
        ...     _ = np.ones((300, 300)) @ np.ones((300, 300))
    """

    def __init__(self, threads: int) -> None:
        if int(threads) < 0:
            raise ValueError(f"BlasThreads: threads must be >= 0, got {threads}")
        self.threads = int(threads)
        self._local = threading.local()

    def __enter__(self) -> BlasThreads:
        depth = getattr(self._local, "depth", 0)
        if depth == 0 and self.threads > 0:
            self._local.limiter = _thread_pools().limit(limits=self.threads, user_api="blas")
        self._local.depth = depth + 1
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._local.depth -= 1
        if self._local.depth == 0:
            limiter = getattr(self._local, "limiter", None)
            self._local.limiter = None
            if limiter is not None:
                limiter.restore_original_limits()
