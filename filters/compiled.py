"""Opt-in ``torch.compile`` of a filter's pure step functions.

At batch 1 a filter step is a few hundred tiny tensor ops and its eager latency is the cost of
dispatching them (a few µs each on CPU). ``torch.compile`` (inductor) fuses them into a few
kernels. The first call per input shape compiles (tens of seconds, a C++ compiler is
needed); later calls run the compiled code. Results equal the eager ones to rounding.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import torch

__all__ = ["CompilableSteps"]


class CompilableSteps:
    """Mixin: ``compile_steps()`` swaps the named pure functions for compiled ones."""

    _STEP_NAMES: ClassVar[tuple[str, ...]] = ()

    def compile_steps(self, enabled: bool = True, **options: Any) -> CompilableSteps:
        """Compile (or, with ``enabled=False``, stop using) the pure step functions that the
        stateful methods call; ``options`` go to :func:`torch.compile`. Returns ``self``.

        Without options, inductor's C++ wrapper is used: it calls the generated kernels from
        C++, which at batch 1 cuts the per-call overhead by about a third.
        """
        compiled = {}
        if not options:
            options = {"options": {"cpp_wrapper": True}}
        if enabled:
            compiled = {
                name: torch.compile(getattr(self, name), **options) for name in self._STEP_NAMES
            }
        self.__dict__["_compiled_steps"] = compiled
        return self

    def step_function(self, name: str) -> Callable[..., Any]:
        """The pure function ``name`` (e.g. ``"step"``): compiled after :meth:`compile_steps`."""
        fn = self.__dict__.get("_compiled_steps", {}).get(name)
        return fn if fn is not None else getattr(self, name)
