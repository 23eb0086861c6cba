"""The line report rules (``evtrack.flow.line_rules``) against a per-window Python reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.flow.line_rules import line_report


def _reference(window, passing, lines, min_lines, share):
    reported, strict = [], []
    for g in range(len(window)):
        same = [k for k in range(len(window)) if window[k] == window[g] and passing[k]]
        lineless = sum(lines[k] == 0 for k in same)
        judged = share < 1.0 and lineless > share * len(same)
        strict.append(judged)
        reported.append(bool(passing[g]) and lines[g] >= min_lines
                        and not (judged and lines[g] == 0))
    return reported, strict


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("share", [0.0, 0.25, 0.5, 1.0])
@pytest.mark.parametrize("min_lines", [0, 1, 2])
def test_line_report_equals_the_per_window_reference(seed, share, min_lines):
    rng = np.random.default_rng(seed)
    window = np.sort(rng.integers(0, 12, 200))
    passing = rng.random(200) < 0.7
    lines = rng.choice([0, 0, 1, 2, 3, 5], 200)
    reported, strict = line_report(torch.from_numpy(window), torch.from_numpy(passing),
                                   torch.from_numpy(lines), min_lines, share)
    want_reported, want_strict = _reference(window, passing, lines, min_lines, share)
    assert reported.tolist() == want_reported
    assert strict.tolist() == want_strict


def test_line_report_of_nothing():
    empty = torch.zeros(0, dtype=torch.int64)
    reported, strict = line_report(empty, empty.bool(), empty, 1, 0.5)
    assert reported.shape == strict.shape == (0,)
