"""Tracker.track sets torch's thread count from its config, within the free cores, and puts
the caller's count back."""

from __future__ import annotations

import pytest
import torch
from tracker_helpers import make_tracker

from evtrack import utils


@pytest.mark.parametrize(("configured", "cores", "expected"), [
    (2, 4, 2), (2, 1, 1), (3, 2, 2), (0, 2, None),  # None: the caller's count is left alone
])
def test_track_runs_on_the_configured_threads(static_sequence, monkeypatch, configured, cores,
                                              expected) -> None:
    tracker, _ = make_tracker(static_sequence, method="pose", torch_threads=configured)
    seen: list[int] = []
    monkeypatch.setattr(tracker, "_track",
                        lambda seq, progress: seen.append(torch.get_num_threads()))
    monkeypatch.setattr(utils, "usable_cpu_count", lambda: cores)
    before = torch.get_num_threads()
    # a caller's count that differs from every expected value, so a leak would show
    torch.set_num_threads(5)
    try:
        tracker.track(static_sequence)
        assert seen == [5 if expected is None else expected]
        assert torch.get_num_threads() == 5
    finally:
        torch.set_num_threads(before)
