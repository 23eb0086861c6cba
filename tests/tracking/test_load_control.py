"""``TrackerConfig.realtime_load``: the search and event budgets follow the processing load.

The load controller is a pure object, driven here with made-up processing times; through a
tracker it reads :attr:`Tracker.clock`, replaced here by fake clocks, so the tests do not
depend on the machine's speed (there are no timed tests).
"""

from __future__ import annotations

from itertools import pairwise

import pytest
from tracker_helpers import make_tracker

from evtrack.errors import ConfigError
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.load_control import LoadController

STREAM_S = 0.01  # one step group: 10 x 1 ms
MIN_EVENTS = 20  # events per step; the fast test sequence has ~100-200 on the object


class _FakeClock:
    """Advances by ``step`` seconds at every call: a step group (timed by two calls) then
    takes ``step`` seconds of processing."""

    def __init__(self, step: float) -> None:
        self.step, self.t, self.calls = step, 0.0, 0

    def __call__(self) -> float:
        self.calls += 1
        self.t += self.step
        return self.t


def _controller(**config) -> LoadController:
    return LoadController.from_config(TrackerConfig.from_dict(config))


def test_config_checks() -> None:
    with pytest.raises(ConfigError, match="max_searched_per_step"):
        TrackerConfig.from_dict({"load": {"realtime": 0.9, "max_searched_per_step": 0}})
    with pytest.raises(ConfigError, match="min_searched_per_step"):
        TrackerConfig.from_dict({"load": {"realtime": 0.9, "max_searched_per_step": 100,
                                          "min_searched_per_step": 200}})
    with pytest.raises(ConfigError, match="load.realtime"):
        TrackerConfig.from_dict({"load": {"realtime": -1.0}})
    with pytest.raises(ConfigError, match="min_events_per_step"):
        TrackerConfig.from_dict({"load": {"realtime": 0.9, "max_events_per_step": 400,
                                          "min_events_per_step": 500}})
    with pytest.raises(ConfigError, match="min_events_per_step"):
        TrackerConfig.from_dict({"load": {"min_events_per_step": -1}})
    # no cap, or no shedding: any floor
    TrackerConfig.from_dict({"load": {"realtime": 0.9, "max_events_per_step": 0,
                                      "min_events_per_step": 500}})
    TrackerConfig.from_dict({"load": {"realtime": 0.9, "max_events_per_step": 400,
                                      "min_events_per_step": 0}})
    assert TrackerConfig().load.realtime == 0.0  # off: deterministic results


def _overload_then_underload(ctl: LoadController, rate: float
                             ) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """60 groups taking twice their stream time, then 600 taking a tenth, each of ``rate``
    events per step (thinned while the event budget is below it): the (search, event)
    budgets after each group."""
    over, under = [], []
    for load, out in ((2.0, over), (0.1, under)):
        for _ in range(60 if load > 1 else 600):
            ctl.events_per_step = rate
            budgets = ctl.adapt(load * STREAM_S, STREAM_S)
            out.append((budgets.search, budgets.events))
    return over, under


def test_sustained_overload_cuts_to_the_floor_and_underload_raises_back() -> None:
    ctl = _controller(load={"realtime": 0.9, "max_searched_per_step": 2000,
                            "min_searched_per_step": 300, "min_events_per_step": 0})
    over, under = _overload_then_underload(ctl, 5000.0)
    budgets = [b for b, _ in over]
    assert budgets[0] == 2000  # the backlog first builds up (5 groups' worth) ...
    assert all(b <= a for a, b in pairwise(budgets))  # ... then only cuts
    assert budgets[-1] == 300 and ctl.search_budget_min == 300
    assert ctl.groups_over_load == 60
    # min_events_per_step 0: no events shed, however long the overload
    assert {e for _, e in over} == {TrackerConfig().load.max_events_per_step}
    assert ctl.event_budget_min == 0
    assert ctl.backlog_s == 0.0 and under[-1][0] == 2000  # drained, raised back
    assert ctl.groups_over_load == 60


@pytest.mark.parametrize("cap", [20_000, 3000, 0])
def test_overload_cuts_the_events_with_the_search_budget(cap) -> None:
    """A lasting overload cuts the events per step together with the search budget, from the
    group's own rate where that is below the cap (or there is none), down to
    ``min_events_per_step``; without a backlog both are raised back, the events to the cap
    (or to no cap)."""
    ctl = _controller(load={"realtime": 0.9, "max_searched_per_step": 2000,
                            "min_searched_per_step": 300, "max_events_per_step": cap,
                            "min_events_per_step": 400})
    rate = 5000.0
    over, under = _overload_then_underload(ctl, rate)
    searched, events = zip(*over, strict=True)
    first = next(i for i, s in enumerate(searched) if s < 2000)
    assert set(events[:first]) == {cap}  # nothing cut while the backlog builds up
    # the first cut: both by the same factor, the events from the rate when below the cap
    factor = searched[first] / 2000
    assert events[first] == int(min(cap or rate, rate) * factor)
    shed = events[first:]
    assert all(b <= a for a, b in pairwise(shed)) and shed[-1] == 400
    assert searched[-1] == 300
    assert ctl.event_budget_min == 400 and ctl.search_budget_min == 300
    searched, events = zip(*under, strict=True)
    assert events[-1] == cap and searched[-1] == 2000
    assert all(b >= a for a, b in pairwise(events[:events.index(cap)]))
    assert all(b >= a for a, b in pairwise(searched))


def test_no_events_are_shed_where_there_are_few() -> None:
    """A group with fewer events per step than ``min_events_per_step`` leaves the event budget:
    thinning could not lower its work."""
    ctl = _controller(load={"realtime": 0.9, "min_events_per_step": 400})
    over, _ = _overload_then_underload(ctl, 300.0)
    assert over[-1][1] == TrackerConfig().load.max_events_per_step
    assert ctl.event_budget_min == 0 and ctl.search_budget_min > 0


def test_events_are_not_shed_without_events() -> None:
    """A method without events (``pose``) has nothing to thin: only the search budget adapts."""
    ctl = _controller(load={"realtime": 0.9, "min_searched_per_step": 300})
    over, _ = _overload_then_underload(ctl, 0.0)
    assert over[-1] == (300, TrackerConfig().load.max_events_per_step)
    assert ctl.event_budget_min == 0


def test_a_single_spike_does_not_cut_the_budget() -> None:
    """A one-off slow group (the first pose's catch-up: 7x the stream time) among groups at
    0.7 of it leaves a backlog that drains, without a cut: the smoothed load counts a group at
    most twice the target."""
    ctl = _controller(load={"realtime": 0.9})
    for _ in range(20):
        ctl.adapt(0.7 * STREAM_S, STREAM_S)
    ctl.adapt(7.3 * STREAM_S, STREAM_S)
    assert ctl.backlog_s > 5 * STREAM_S
    for _ in range(40):
        ctl.adapt(0.7 * STREAM_S, STREAM_S)
    assert ctl.search_budget_min == 0
    assert ctl.budgets.search == TrackerConfig().load.max_searched_per_step


@pytest.mark.parametrize("processing_s, lowered", [(2 * STREAM_S, True), (0.1 * STREAM_S, False)])
def test_tracking_adapts_the_budget_to_the_clock(fast_sequence, processing_s, lowered) -> None:
    """Through :meth:`Tracker.track`: a clock on which each step group takes twice its stream
    time lowers the budget to the floor; one on which it takes a tenth leaves it."""
    # groups of STREAM_S (10 steps): the 0.6 s sequence then has the ~27 groups the budget
    # needs to build a backlog and be cut from 2000 to 200
    tracker, _ = make_tracker(fast_sequence, flow_batch_steps=10,
                              load={"realtime": 0.9, "max_searched_per_step": 2000,
                                    "min_searched_per_step": 200,
                                    "min_events_per_step": MIN_EVENTS})
    tracker.clock = _FakeClock(processing_s)
    tracker.track(fast_sequence)
    st = tracker.stats
    groups = st.steps // tracker.config.flow_batch_steps
    assert tracker.clock.calls >= 2 * groups
    if lowered:  # both budgets down to their floors
        assert st.search_budget_min == 200 and tracker.load.budgets.search == 200
        assert st.groups_over_load >= groups
        assert st.event_budget_min == MIN_EVENTS == tracker.load.budgets.events
        assert st.events_thinned > 0
    else:
        assert st.search_budget_min == 0 and tracker.load.budgets.search == 2000
        assert st.groups_over_load == 0
        assert st.event_budget_min == 0 and st.events_thinned == 0


def test_off_by_default_the_clock_is_not_read(fast_sequence) -> None:
    tracker, _ = make_tracker(fast_sequence)

    def no_clock() -> float:
        raise AssertionError("the clock was read with realtime_load off")

    tracker.clock = no_clock
    tracker.track(fast_sequence)
    assert tracker.stats.search_budget_min == 0 and tracker.stats.groups_over_load == 0
    assert tracker.stats.event_budget_min == 0


def _cut_to_the_floors(ctl: LoadController, rate: float = 5000.0) -> None:
    """Groups at twice their stream time until both budgets are at their floors."""
    for _ in range(200):
        ctl.events_per_step = rate
        budgets = ctl.adapt(2 * STREAM_S, STREAM_S)
        if (budgets.search, budgets.events) == (ctl.min_search, ctl.min_events):
            return
    raise AssertionError("the budgets did not reach their floors")


def test_a_group_under_the_target_is_not_cut_for_the_smoothed_loads_lag() -> None:
    """After a long overload the smoothed load stays over the target for several groups once
    the groups themselves are under it: those groups cut nothing (the smoothed load's lag
    used to cut on down to the floors)."""
    ctl = _controller(load={"realtime": 0.9})
    for _ in range(5):  # a backlog over 5 groups and a smoothed load over the target: a cut
        ctl.events_per_step = 5000.0
        ctl.adapt(2 * STREAM_S, STREAM_S)
    before = (ctl.budgets.search, ctl.budgets.events)
    assert ctl.min_search < before[0] < ctl.max_search
    assert ctl.min_events < before[1] < 5000  # both can still be cut
    for _ in range(3):  # each at 0.85: under the target, the smoothed load still above it
        ctl.adapt(0.85 * STREAM_S, STREAM_S)
        assert ctl.load > 0.9 and ctl.backlog_s > 5 * STREAM_S
        assert (ctl.budgets.search, ctl.budgets.events) == before


def test_budgets_rise_while_a_backlog_drains_well_under_the_target() -> None:
    """At the floors a machine that then runs at half the target raises both budgets while
    the backlog is still draining; at just under the target (above 0.8 of it) they hold
    until it has drained."""
    for load, rises in ((0.45, True), (0.85, False)):
        ctl = _controller(load={"realtime": 0.9})
        _cut_to_the_floors(ctl)
        floors = (ctl.budgets.search, ctl.budgets.events)
        seen = []
        for _ in range(40):
            ctl.adapt(load * STREAM_S, STREAM_S)
            if ctl.backlog_s > 0:
                seen.append((ctl.budgets.search, ctl.budgets.events))
        assert seen, "the backlog drained at once"
        if rises:
            assert seen[-1][0] > floors[0] and seen[-1][1] > floors[1]
        else:
            assert set(seen) == {floors}
