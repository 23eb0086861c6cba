"""The step scheduler's arithmetic (evtrack.tracking.scheduler): step groups covering a span,
and the runs of steps that nothing falls between, against a step-by-step reference."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.tracking.scheduler import group_spans, quiet_end


@pytest.mark.parametrize(("start", "end", "group"), [(0, 40_000, 10_000), (3_000, 47_000, 10_000),
                                                     (5_000, 5_000, 10_000), (7, 8, 40)])
def test_group_spans_cover_the_span_cut_at_the_group_multiples(start, end, group) -> None:
    spans = group_spans(start, end, group)
    if start >= end:
        assert spans == []
        return
    assert spans[0][0] == start and spans[-1][1] == end
    assert all(a1 == b0 for (_, a1), (b0, _) in zip(spans, spans[1:], strict=False))
    assert all(g1 % group == 0 for _, g1 in spans[:-1])
    assert all(0 < g1 - g0 <= group for g0, g1 in spans)


def _quiet_end_reference(t0, k, n_steps, step, frame, due, expires) -> int:
    """Step by step from ``k``: step ``j`` joins the run while no frame is taken at its start
    (for ``j > k``: the frames before its end, ``t0 + (j + 1) step``, are; step k's were taken
    before the run), no measurement is due at its end, and the depth map read at its start
    (``t0 + j step``) has not expired."""
    j = k
    while j < n_steps:
        end_j = t0 + (j + 1) * step
        frame_ok = j == k or frame is None or frame >= end_j
        due_ok = due is None or due > end_j
        depth_ok = expires is None or t0 + j * step <= expires
        if not (frame_ok and due_ok and depth_ok):
            break
        j += 1
    return j


def test_quiet_end_equals_the_step_by_step_reference() -> None:
    rng = np.random.default_rng(0)
    step = 1000
    for _ in range(5000):
        t0 = int(rng.integers(0, 50)) * 40_000
        n_steps = int(rng.integers(1, 41))
        k = int(rng.integers(0, n_steps))
        frame = None if rng.random() < 0.3 else t0 + int(rng.integers(-5_000, 60_000))
        due = None if rng.random() < 0.3 else t0 + int(rng.integers(-5_000, 60_000))
        expires = None if rng.random() < 0.3 else t0 + float(rng.integers(-5_000, 60_000))
        got = quiet_end(t0, k, n_steps, step, frame, due, expires)
        ref = _quiet_end_reference(t0, k, n_steps, step, frame, due, expires)
        # an end at or before k means no step is quiet (the scheduler then runs no run)
        assert max(got, k) == ref, (t0, k, n_steps, frame, due, expires, got, ref)


def test_quiet_end_without_anything_pending_is_the_group_end() -> None:
    assert quiet_end(0, 3, 40, 1000, None, None, None) == 40
    assert quiet_end(0, 3, 40, 1000, None, None, 1e9) == 40
