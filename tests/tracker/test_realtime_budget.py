"""``TrackerConfig.realtime_load``: the search budget follows the processing load.

The controller is driven through :attr:`Tracker.clock`, replaced here by fake clocks, so the
tests do not depend on the machine's speed (there are no timed tests).
"""

from __future__ import annotations

from itertools import pairwise

import pytest
from tracker_helpers import make_tracker

from evtrack.errors import ConfigError
from evtrack.tracker import Tracker
from evtrack.tracking_config import TrackerConfig

STREAM_S = 0.01  # one step group: 10 x 1 ms


class _FakeClock:
    """Advances by ``step`` seconds at every call: a step group (timed by two calls) then
    takes ``step`` seconds of processing."""

    def __init__(self, step: float) -> None:
        self.step, self.t, self.calls = step, 0.0, 0

    def __call__(self) -> float:
        self.calls += 1
        self.t += self.step
        return self.t


def _bare_tracker(**config) -> Tracker:
    import numpy as np

    from evtrack.camera import PinholeCamera

    cam = PinholeCamera(100.0, 100.0, 49.5, 49.5, 100, 100)
    cube = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])
    return Tracker(TrackerConfig.from_dict(config), camera=cam, mesh=cube)


def test_config_checks() -> None:
    with pytest.raises(ConfigError, match="max_searched_per_step"):
        TrackerConfig.from_dict({"realtime_load": 0.9, "max_searched_per_step": 0})
    with pytest.raises(ConfigError, match="min_searched_per_step"):
        TrackerConfig.from_dict({"realtime_load": 0.9, "max_searched_per_step": 100,
                                 "min_searched_per_step": 200})
    with pytest.raises(ConfigError, match="realtime_load"):
        TrackerConfig.from_dict({"realtime_load": -1.0})
    assert TrackerConfig().realtime_load == 0.0  # off: deterministic results


def test_sustained_overload_cuts_to_the_floor_and_underload_raises_back() -> None:
    tracker = _bare_tracker(realtime_load=0.9, max_searched_per_step=2000,
                            min_searched_per_step=300)
    budgets = []
    for _ in range(60):  # every group takes twice its stream time
        tracker._adapt_search_budget(2 * STREAM_S, STREAM_S)
        budgets.append(tracker._search_budget)
    assert budgets[0] == 2000  # the backlog first builds up (5 groups' worth) ...
    assert all(b <= a for a, b in pairwise(budgets))  # ... then only cuts
    assert budgets[-1] == 300 and tracker.stats.search_budget_min == 300
    assert tracker.stats.groups_over_load == 60
    for _ in range(400):  # then every group takes a tenth: the backlog drains, it raises
        tracker._adapt_search_budget(0.1 * STREAM_S, STREAM_S)
    assert tracker._backlog_s == 0.0 and tracker._search_budget == 2000
    assert tracker.stats.groups_over_load == 60


def test_a_single_spike_does_not_cut_the_budget() -> None:
    """A one-off slow group (the first pose's catch-up: 7x the stream time) among groups at
    0.7 of it leaves a backlog that drains, without a cut: the smoothed load counts a group at
    most twice the target."""
    tracker = _bare_tracker(realtime_load=0.9)
    for _ in range(20):
        tracker._adapt_search_budget(0.7 * STREAM_S, STREAM_S)
    tracker._adapt_search_budget(7.3 * STREAM_S, STREAM_S)
    assert tracker._backlog_s > 5 * STREAM_S
    for _ in range(40):
        tracker._adapt_search_budget(0.7 * STREAM_S, STREAM_S)
    assert tracker.stats.search_budget_min == 0
    assert tracker._search_budget == TrackerConfig().max_searched_per_step


@pytest.mark.parametrize("processing_s, lowered", [(2 * STREAM_S, True), (0.1 * STREAM_S, False)])
def test_tracking_adapts_the_budget_to_the_clock(fast_sequence, processing_s, lowered) -> None:
    """Through :meth:`Tracker.track`: a clock on which each step group takes twice its stream
    time lowers the budget to the floor; one on which it takes a tenth leaves it."""
    # groups of STREAM_S (10 steps): the 0.6 s sequence then has the ~27 groups the budget
    # needs to build a backlog and be cut from 2000 to 200
    tracker, _ = make_tracker(fast_sequence, realtime_load=0.9, max_searched_per_step=2000,
                              min_searched_per_step=200, flow_batch_steps=10)
    tracker.clock = _FakeClock(processing_s)
    tracker.track(fast_sequence)
    groups = tracker.stats.steps // tracker.config.flow_batch_steps
    assert tracker.clock.calls >= 2 * groups
    if lowered:
        assert tracker.stats.search_budget_min == 200 and tracker._search_budget == 200
        assert tracker.stats.groups_over_load >= groups
    else:
        assert tracker.stats.search_budget_min == 0 and tracker._search_budget == 2000
        assert tracker.stats.groups_over_load == 0


def test_off_by_default_the_clock_is_not_read(fast_sequence) -> None:
    tracker, _ = make_tracker(fast_sequence)

    def no_clock() -> float:
        raise AssertionError("the clock was read with realtime_load off")

    tracker.clock = no_clock
    tracker.track(fast_sequence)
    assert tracker.stats.search_budget_min == 0 and tracker.stats.groups_over_load == 0
