"""Real-time load control (``TrackerConfig.load.realtime``): from the processing time of each
step group and its stream time, the search and event budgets per velocity step of the next
groups. A pure object: it reads no clock and no tracker state."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from evtrack.tracking.config import TrackerConfig

__all__ = ["Budgets", "LoadController"]

LOAD_SMOOTHING = 0.1
"""Weight of the newest step group in the smoothed load and events per step (~10 groups) ..."""
LOAD_CLIP = 2.0
"""... whose single groups count at most this many times the target (a one-off spike, such as
the first pose's catch-up, is not a trend)."""
BACKLOG_GROUPS = 5
"""The backlog (processing time beyond the target) that starts cutting the budgets, in step
groups' stream time (200 ms at the default 40 x 1 ms)."""
RAISE_SHARE = 0.8
"""Below this share of the target the smoothed load raises the budgets while a backlog still
drains (at the floors a small machine's load can sit there: without it the budgets stayed at
their floors until the backlog had drained)."""
BUDGET_CUT = 0.9
BUDGET_CUT_MAX = 0.7
BUDGET_RAISE = 1.05
"""Factors of the budgets per step group: a cut (while the backlog is over ``BACKLOG_GROUPS``)
by ``target / smoothed load`` within ``[BUDGET_CUT_MAX, BUDGET_CUT]`` (0.7 at twice the target,
the smoothed load's clip), and a raise."""


@dataclass(frozen=True)
class Budgets:
    """Per velocity step: ``search`` events searched for candidates, ``events`` events entering
    the flow (0: no cap)."""

    search: int
    events: int


def _lowest(seen: int, budget: int, ceiling: int) -> int:
    """The record of the lowest budget set: ``seen`` (0: none yet) or ``budget`` where that is
    lower and not the configured ``ceiling``."""
    return budget if budget != ceiling and (not seen or budget < seen) else seen


class LoadController:
    """Budgets that keep the processing near ``target`` of the stream time.

    The processing time beyond ``target`` of the stream time accumulates as a backlog (a live
    stream's events waiting), which drains when the groups take less. While the backlog exceeds
    ``BACKLOG_GROUPS`` groups' stream time and the load, smoothed over ~10 groups and the
    group's own, is above the target (the group's own keeps the smoothed one's lag from cutting
    on), both budgets are cut per group by ``target / load`` (within ``BUDGET_CUT_MAX`` and
    ``BUDGET_CUT``):

    - the search budget down to ``min_search``;
    - the event budget (events thinned by cells, as by ``max_events``) down to ``min_events``,
      from the events per step (smoothed over ~10 groups, :meth:`observe_events`) where those
      are fewer than the budget or there is no cap; not where they are fewer than
      ``min_events`` already.

    While the smoothed load is below the target and there is no backlog, or it is below
    ``RAISE_SHARE`` of the target, both grow by ``BUDGET_RAISE`` per group, towards
    ``max_search`` and ``max_events`` (or no cap, once the budget is twice the events per step);
    otherwise they hold. The average load so stays near the target with a bounded delay where
    the floors allow it; a burst the budgets cannot absorb (e.g. the first pose's catch-up) only
    drains. Cutting both together costs less accuracy than cutting the search alone to a low
    floor (cracker box `faster`: 2500 events and 1000 searched per step, 3.6 cm / 8.7 deg, ran
    about as fast as 2000 and 250, 9.5 cm / 16.6 deg, on 2 cores of an AMD EPYC).

    Args:
        target: processing time / stream time aimed at (``load.realtime``; 0: budgets fixed).
        max_search, min_search: the search budget's ceiling and floor per step
            (``load.max_searched_per_step``, ``load.min_searched_per_step``).
        max_events, min_events: the event budget's ceiling (0: none) and floor per step
            (``load.max_events_per_step``, ``load.min_events_per_step``).

    Attributes:
        budgets: the current :class:`Budgets`.
        events_per_step: events per step entering the thinning, smoothed (``None`` before any).
        backlog_s: processing time beyond the target, not yet drained (s).
        load: smoothed processing / stream time (``None`` before any group).
        search_budget_min, event_budget_min: the lowest budgets set (0: never lowered).
        groups_over_load: groups whose processing took longer than the target.
    """

    def __init__(self, target: float, max_search: int, min_search: int, max_events: int,
                 min_events: int) -> None:
        self.target = float(target)
        self.max_search, self.min_search = int(max_search), int(min_search)
        self.max_events, self.min_events = int(max_events), int(min_events)
        self.reset()

    @classmethod
    def from_config(cls, config: TrackerConfig) -> LoadController:
        """The controller of a tracker's config (``load.realtime`` and the budgets)."""
        return cls(config.load.realtime, config.load.max_searched_per_step,
                   config.load.min_searched_per_step, config.load.max_events_per_step,
                   config.load.min_events_per_step)

    def reset(self) -> None:
        """Back to the configured budgets, no history."""
        self.budgets = Budgets(self.max_search, self.max_events)
        self.events_per_step: float | None = None
        self.backlog_s = 0.0
        self.load: float | None = None
        self.search_budget_min = 0
        self.event_budget_min = 0
        self.groups_over_load = 0

    def observe_events(self, per_step: float) -> None:
        """Count a step group's events per step (before thinning) into the smoothed rate."""
        self.events_per_step = per_step if self.events_per_step is None else (
            LOAD_SMOOTHING * per_step + (1 - LOAD_SMOOTHING) * self.events_per_step)

    def adapt(self, wall_s: float, stream_s: float) -> Budgets:
        """The budgets of the next groups after a group that took ``wall_s`` seconds to
        process ``stream_s`` seconds of the stream."""
        target = self.target
        load = wall_s / stream_s
        if load > target:
            self.groups_over_load += 1
        counted = min(load, LOAD_CLIP * target)
        self.load = counted if self.load is None else (
            LOAD_SMOOTHING * counted + (1 - LOAD_SMOOTHING) * self.load)
        self.backlog_s = max(0.0, self.backlog_s + wall_s - target * stream_s)
        search, events = self.budgets.search, self.budgets.events
        if self.backlog_s > BACKLOG_GROUPS * stream_s and self.load > target < load:
            search, events = self._cut(search, events)
        elif self.load < target and (self.backlog_s == 0.0 or self.load < RAISE_SHARE * target):
            search, events = self._raise(search, events)
        self.search_budget_min = _lowest(self.search_budget_min, search, self.max_search)
        self.event_budget_min = _lowest(self.event_budget_min, events, self.max_events)
        self.budgets = Budgets(search, events)
        return self.budgets

    def _cut(self, search: int, events: int) -> tuple[int, int]:
        cut = min(max(self.target / self.load, BUDGET_CUT_MAX), BUDGET_CUT)
        search = max(int(search * cut), self.min_search)
        if (self.events_per_step or 0.0) > self.min_events > 0:  # thinning can help
            rate = math.ceil(self.events_per_step)
            base = min(events, rate) if events else rate
            events = max(int(base * cut), self.min_events)
        return search, events

    def _raise(self, search: int, events: int) -> tuple[int, int]:
        search = min(int(search * BUDGET_RAISE) + 1, self.max_search)
        if events and events != self.max_events:
            events = int(events * BUDGET_RAISE) + 1
            if self.max_events:
                events = min(events, self.max_events)
            elif events > 2 * (self.events_per_step or 0.0):
                events = 0  # far above the events: back to no cap
        return search, events
