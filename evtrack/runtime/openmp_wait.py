"""OpenMP's wait policy: let idle worker threads sleep instead of spinning.

torch and the flow's compiled kernels (numba's ``omp`` layer) share one GNU OpenMP runtime.
Its worker threads spin for a while after every parallel region before they sleep. The
tracker runs a few short parallel kernels every 5-10 ms and tiny serial steps in between, so on a
machine with as many busy threads as cores the spinning workers take the cores from the main
thread, and a parallel region waits a whole scheduler slice (4-70 ms) for a worker that was
descheduled. ``OMP_WAIT_POLICY=PASSIVE`` makes idle workers sleep at once. Measured with
``benchmarks/bench_tracker.py`` on the ``faster`` YCB sequences (2 cores, 2 threads), the full
tracker's processing time fell by 25-30 % (mustard bottle 9.3 s -> 6.7 s for a 2 s sequence)
and the 3.8 M events/s box was unchanged.

The runtime reads the variable once, when it is loaded (with torch). :func:`prefer_passive_wait`
therefore sets it only when torch is not loaded yet (``import evtrack`` before ``import torch``,
or the ``evtrack`` command) and only when the variable is unset: to keep the runtime's default,
set ``OMP_WAIT_POLICY`` yourself (``ACTIVE`` or ``PASSIVE``) before starting Python.

Importing this module (``evtrack/__init__.py`` does it first) calls :func:`prefer_passive_wait`.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping, MutableMapping

__all__ = ["WAIT_POLICY_VARIABLE", "prefer_passive_wait", "wait_policy"]

WAIT_POLICY_VARIABLE = "OMP_WAIT_POLICY"


def prefer_passive_wait(environ: MutableMapping[str, str] | None = None,
                        modules: Mapping[str, object] | None = None) -> bool:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` when it is unset and torch is not loaded yet.

    Args:
        environ: the environment to change (default ``os.environ``).
        modules: the loaded modules (default ``sys.modules``).

    Returns:
        Whether the variable was set (False: it was set already, or torch's OpenMP runtime
        is loaded and would not read it).
    """
    environ = os.environ if environ is None else environ
    modules = sys.modules if modules is None else modules
    if WAIT_POLICY_VARIABLE in environ or "torch" in modules:
        return False
    environ[WAIT_POLICY_VARIABLE] = "PASSIVE"
    return True


def wait_policy() -> str:
    """The wait policy in this process's environment, for reports: its value or ``"default"``."""
    return os.environ.get(WAIT_POLICY_VARIABLE, "default")


prefer_passive_wait()
