"""The flow's selection hash (:func:`hash32`), for tensors, arrays and the compiled kernels.

The registration keeps the events and hypotheses of smallest hash (its caps), the sampled
search the events of hash below a threshold, and the budget visits RoI cells in the order of
their hash: all the same function, so that these selections agree.
"""

from __future__ import annotations

from typing import TypeVar

from evtrack.flow.constants import HASH_MULTIPLIER
from evtrack.flow.numba_support import kernel

__all__ = ["hash32", "hash32_kernel"]

V = TypeVar("V")


def hash32(value: V) -> V:
    """A deterministic 32-bit multiplicative hash of int64 values (no overflow): ``((value &
    0x7FFFFFFF) * HASH_MULTIPLIER) & 0xFFFFFFFF``, in ``[0, 2^32)``.

    Args:
        value: int64 tensor or array (any shape), or a Python int.

    Returns:
        The hashes, of ``value``'s type and shape.
    """
    return ((value & 0x7FFFFFFF) * HASH_MULTIPLIER) & 0xFFFFFFFF


hash32_kernel = kernel()(hash32)
""":func:`hash32` compiled, for one int64 inside the numba kernels."""
