"""Constants shared by the flow's modules: units, the time limits of the searches' integer
state, the registration's exact arithmetic and the selection hash.

Timestamps are integer µs and flows px/s throughout the flow.
"""

from __future__ import annotations

__all__ = [
    "US_PER_S",
    "MAX_DT_US",
    "T_LIMIT",
    "T_KEEP",
    "MAX_SPAN_US",
    "EMPTY_T",
    "NO_EVENT",
    "COST_SCALE",
    "Q_MAX",
    "RANK_BITS",
    "PARALLEL_EPS",
    "IRLS_DELTA",
    "HASH_MULTIPLIER",
    "HASH_RANGE",
]

# ---------------------------------------------------------------------- units and time limits
US_PER_S = 1_000_000
"""Microseconds per second (timestamps are µs, flows px/s)."""

MAX_DT_US = 1 << 27
"""Largest time difference (µs, ~134 s) the integer ring buffer resolves; speed bounds must
keep every candidate's ``t_k - t_i`` below it."""

T_LIMIT = 1 << 29
"""Relative timestamps (µs) of the searches' state stay below this; the base moves forward
before they reach it."""

T_KEEP = 1 << 28
"""After a rebase, entries at most this old (µs) keep their value (older ones are emptied:
they are beyond any speed bound, see ``FlowConfig``)."""

MAX_SPAN_US = 1 << 27
"""Longest time span (µs) of the events of one chunk (the searches split longer chunks)."""

EMPTY_T = -(1 << 30)
"""Relative timestamp (µs) of an empty history slot: ``t - EMPTY_T`` exceeds every speed
bound and still fits int32 for ``0 <= t < T_LIMIT``."""

NO_EVENT = -(1 << 31)
"""``last`` of a pixel without an event in the compiled search's int32 state
(``last = 2 * t + (p > 0)`` otherwise)."""

# ---------------------------------------------------------------------- registration
COST_SCALE = 16.0
"""Distances are rounded to 1 / COST_SCALE px/s before the exact int64 sums."""

Q_MAX = 1 << 25
"""Rounded distances are capped here (2^25 / COST_SCALE = 2.1 M px/s, beyond any plausible
difference of flows); below it ``(n +- 0.5)^2`` is exact in float64."""

RANK_BITS = 20
"""Bits of a hypothesis' rank in the ``(cost << RANK_BITS) | rank`` arg-min keys."""

PARALLEL_EPS = 1e-3
"""Two candidates are parallel when ``cross^2 <= PARALLEL_EPS^2 |a|^2 |b|^2``."""

IRLS_DELTA = 0.01
"""Smallest residual of the IRLS weights, as a fraction of ``max(|F|, 1)`` (px/s)."""

# ---------------------------------------------------------------------- selection hash
HASH_MULTIPLIER = 2654435761
"""Knuth's multiplicative constant (``2^32`` over the golden ratio) of
:func:`evtrack.flow.hashing.hash32`."""

HASH_RANGE = 1 << 32
"""The hash's values lie in ``[0, HASH_RANGE)``."""
