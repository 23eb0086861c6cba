"""numpy's BLAS threads while the tracker runs: one, so that idle BLAS workers do not spin.

numpy's wheels bring OpenBLAS, which starts its worker threads when numpy is imported. After
a BLAS call large enough to be split across them, the workers busy-wait for the next call for
a while before they sleep. The tracker's event mask used to be such a call (an (N, 2) by
(2, edges) product on every flow call): one worker was running in 82 % of the samples of a
2 s ``faster`` run and took a core from the flow's kernels and the filters. The mask no
longer uses BLAS (:func:`evtrack.tracking.silhouette.pixels_in_polygon`); the limit stays so that no
other product can start the spinning again. ``benchmarks/bench_tracker_cpu.py`` on the
cracker box ``faster`` sequence (2 cores, medians of 2 interleaved runs): 34.4 s with
OpenBLAS's own threads, 33.6 s with one BLAS thread, 28.8 s when the flow's search strips
came on top (single runs with BLAS spinning showed the strips gaining nothing: their second
thread had no free core).

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
