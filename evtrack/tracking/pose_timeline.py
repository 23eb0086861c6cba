"""A pose filter with its recent past, so that late measurements are fused at their own time.

A pose network needs time: the pose of the frame taken at ``t`` reaches the filter at
``t + latency``, when the filter has already moved on. :class:`PoseTimeline` keeps a snapshot
of the filter state at the end of every step of the last ``horizon_us`` and every measurement
of that span. A measurement for a past time ``t_m`` rolls the filter back to the last step end
before ``t_m``, and replays the steps from there, fusing every kept measurement at its own time
(predict to it, update, predict on). The result is the state the filter would have reached had
the measurement arrived on time; the past outputs of the tracker are not rewritten (they were
the best estimates available then).

Snapshots hold the filter's whole state, counters included (:class:`~evtrack.filters.PoseUKF`:
``t, q, cov, initialized, rejected_run, rejected, reinitialised``; :class:`PoseTwistUKF` adds
``twist``), so a replayed measurement is counted once.
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from evtrack.filters import PoseTwistUKF, PoseUKF

__all__ = ["PoseTimeline", "Measurement"]

_STATE_NAMES = ("t", "q", "cov", "twist", "bias", "initialized", "rejected_run", "rejected",
                "reinitialised")


class _RunStepSnapshot(Sequence[Tensor]):
    """The snapshot of one step of a :meth:`PoseUKF.predict_run
    <evtrack.filters.PoseUKF.predict_run>`, built on access: the state tensors ``t``, ``q``,
    ``cov`` are views of the run's stacked states at the step, the others (counters, which a
    predict leaves unchanged) those of the run's final snapshot. It reads like the tuple of
    tensors :meth:`PoseTimeline._snapshot` returns; a run of n steps so costs n small
    objects instead of 3n tensor views, most of which are never read (only the steps a late
    measurement rolls back to are)."""

    __slots__ = ("_states", "_index", "_last", "_slots")

    def __init__(self, states: tuple[Tensor, Tensor, Tensor], index: int,
                 last: tuple[Tensor, ...], slots: tuple[int | None, ...]) -> None:
        self._states, self._index, self._last, self._slots = states, index, last, slots

    def __len__(self) -> int:
        return len(self._last)

    def __getitem__(self, m: int) -> Tensor:  # type: ignore[override]
        slot = self._slots[m]
        return self._last[m] if slot is None else self._states[slot][self._index]


@dataclass
class Measurement:
    """A measurement for the pose filter.

    Attributes:
        t_us: the time it describes (µs).
        kind: ``"pose"`` (``value`` = (t (1,3), q (1,4))), ``"pose_reinit"`` (a pose that
            re-initialises the filter if its gate rejects it), ``"twist"`` (``value`` = (1,6)) or
            ``"range"`` (``value`` = (direction (1,3), distance (1,)): the position's component
            along a direction, see :meth:`~evtrack.filters.PoseUKF.update_range`) or
            ``"aligned"`` (``value`` = (t (1,3), q (1,4)): a pose fitted from the filter's own,
            e.g. on a depth frame, see :meth:`~evtrack.filters.PoseUKF.update_aligned`).
        value: see ``kind``.
        cov: (1,6,6) covariance, or ``None`` for the filter's default; for a range, its (1,)
            variance (m²).
        seq: insertion order (ties at the same time are fused in this order).
    """

    t_us: int
    kind: str
    value: tuple[Tensor, ...]
    cov: Tensor | None
    seq: int = 0


class PoseTimeline:
    """Step a pose filter and fuse measurements at their own (past) times.

    Args:
        filt: a :class:`PoseUKF` (predicted with a twist per step) or :class:`PoseTwistUKF`
            (constant-velocity predict) with batch size 1.
        horizon_us: how much past (µs) is kept; older measurements are dropped and counted in
            :attr:`late`.
    """

    batch_replay: bool = True
    """Replay the steps without a measurement in one compiled call each run (see
    :meth:`_replay`); off: step by step (the tests compare the two)."""

    def __init__(self, filt: PoseUKF | PoseTwistUKF, horizon_us: int) -> None:
        if filt.batch_size != 1:
            raise ValueError(f"PoseTimeline needs a filter of batch size 1, got {filt.batch_size}")
        self.filter = filt
        self.twist_driven = isinstance(filt, PoseUKF)
        buffers = dict(filt.named_buffers(recurse=False))
        self.names = tuple(n for n in _STATE_NAMES if n in buffers)
        # per state tensor: its index in predict_run's (t, q, cov), None for the others
        self._run_slots = tuple({"t": 0, "q": 1, "cov": 2}.get(n) for n in self.names)
        self.horizon_us = int(horizon_us)
        self.late = 0
        self._seq = 0
        self.start(0)

    # ------------------------------------------------------------------ state
    @property
    def now(self) -> int:
        """Time of the current state (µs)."""
        return self._times[-1]

    def step_ends(self, t_from: int, t_to: int) -> list[int]:
        """The kept step ends (µs) in ``(t_from, t_to]``, in time order."""
        times = self._times
        lo = bisect.bisect_right(times, int(t_from))
        hi = bisect.bisect_right(times, int(t_to))
        return [times[i] for i in range(lo, hi)]

    def start(self, t_us: int) -> None:
        """Forget the past: the current filter state is the state at ``t_us``."""
        self._times: deque[int] = deque([int(t_us)])
        # per state tensor: (the filter's tensor, its version, the copy) at the last snapshot
        self._copies: list[tuple[Tensor, int | None, Tensor] | None] = [None] * len(self.names)
        self._base = self._snapshot()  # the state at the start, before any measurement
        self._base_open = True  # measurements at exactly the start time may still come
        self._snaps: deque[Sequence[Tensor]] = deque([self._base])
        self._twists: deque[Tensor | None] = deque([None])
        self._records: list[Measurement] = []

    def _snapshot(self) -> tuple[Tensor, ...]:
        """Copies of the filter's state tensors. A tensor that is the same object, unchanged
        in place (same version counter), since the last snapshot shares that snapshot's copy
        (snapshots are never written to; :meth:`_restore` copies them), so the counters that
        change once in a thousand steps are not copied every step."""
        buf = self.filter._buffers
        last = self._copies
        out = []
        for i, name in enumerate(self.names):
            x = buf[name]
            prev = last[i]
            if prev is not None and prev[0] is x and not x.is_inference() \
                    and prev[1] == x._version:
                out.append(prev[2])
            else:
                copy = x.clone()
                last[i] = (x, None if x.is_inference() else x._version, copy)
                out.append(copy)
        return tuple(out)

    def _restore(self, snap: Sequence[Tensor]) -> None:
        for name, value in zip(self.names, snap, strict=True):
            setattr(self.filter, name, value.clone())

    # ------------------------------------------------------------------ stepping
    def _predict(self, dt_us: int, twist: Tensor | None) -> None:
        if dt_us <= 0:
            return
        dt = dt_us * 1e-6
        if self.twist_driven:
            self.filter.predict(twist, dt)
        else:
            self.filter.predict(dt)

    def _fuse(self, m: Measurement) -> None:
        if m.kind == "pose":
            self.filter.update(m.value[0], m.value[1], m.cov)
        elif m.kind == "pose_reinit":
            self.filter.update(m.value[0], m.value[1], m.cov, reinit_after=1)
        elif m.kind == "range":
            self.filter.update_range(m.value[0], m.value[1], m.cov)
        elif m.kind == "aligned":
            self.filter.update_aligned(m.value[0], m.value[1], m.cov)
        else:
            self.filter.update_twist(m.value[0], m.cov)

    def step(self, t1_us: int, twist: Tensor | None = None) -> None:
        """Predict from :attr:`now` to ``t1_us`` (with ``twist`` (1,6) for a :class:`PoseUKF`)."""
        t1_us = int(t1_us)
        if t1_us <= self.now:
            raise ValueError(f"PoseTimeline.step: {t1_us} µs is not after {self.now} µs")
        if self.twist_driven and twist is None:
            raise ValueError("PoseTimeline.step: a twist-driven filter needs a twist")
        self._predict(t1_us - self.now, twist)
        self._times.append(t1_us)
        self._snaps.append(self._snapshot())
        self._twists.append(None if twist is None else twist.clone())
        self._trim()

    def _trim(self) -> None:
        limit = self.now - self.horizon_us
        while len(self._times) > 1 and self._times[1] <= limit:
            self._base_open = False
            self._times.popleft()
            self._snaps.popleft()
            self._twists.popleft()
        first = self._times[0]
        if not self._base_open and self._records and self._records[0].t_us <= first:
            self._records = [m for m in self._records if m.t_us > first]

    # ------------------------------------------------------------------ measurements
    def add(self, t_us: int, kind: str, value: tuple[Tensor, ...], cov: Tensor | None = None
            ) -> bool:
        """Fuse a measurement for time ``t_us`` <= :attr:`now`.

        Returns:
            False when it is older than the kept past (dropped, counted in :attr:`late`).
        """
        t_us = int(t_us)
        if t_us > self.now:
            raise ValueError(f"measurement at {t_us} µs is in the future of the filter "
                             f"({self.now} µs)")
        if t_us < self._times[0] or (t_us == self._times[0] and not self._base_open):
            self.late += 1
            return False
        self._seq += 1
        m = Measurement(t_us, kind, value, cov, self._seq)
        keys = [(r.t_us, r.seq) for r in self._records]
        self._records.insert(bisect.bisect(keys, (m.t_us, m.seq)), m)
        times = list(self._times)
        j = bisect.bisect_left(times, t_us) - 1  # last step end strictly before t_us
        if j < 0:  # at the start time itself: from the state before any measurement
            j = 0
            self._restore(self._base)
            for r in self._records:
                if r.t_us == times[0]:
                    self._fuse(r)
            self._snaps[0] = self._snapshot()
        else:
            self._restore(self._snaps[j])
        self._replay(j, times)
        return True

    def _replay(self, j: int, times: list[int],
                twist_of: Callable[[int, int], Tensor | None] | None = None,
                t_from: int = 0) -> None:
        """From the state of step end ``j`` (restored), redo the steps after it, fusing the
        kept measurements at their times; ``twist_of`` (see :meth:`remeasure`) may replace
        the twist of each step starting at or after ``t_from`` first. Without ``twist_of``,
        each run of steps without a measurement is predicted in one call
        (:meth:`PoseUKF.predict_run <evtrack.filters.PoseUKF.predict_run>`, where it
        applies and :attr:`batch_replay` is set): the same states, bit for bit."""
        i = j + 1
        if twist_of is None and self.batch_replay and self.twist_driven:
            # the steps holding a measurement: r in (times[i - 1], times[i]] -> step i
            measured = {bisect.bisect_left(times, r.t_us) for r in self._records}
            while i < len(times):
                end = i
                while end < len(times) and end not in measured:
                    end += 1
                if end - i < 2:
                    self._replay_step(i, times, None, t_from)
                    i += 1
                elif self._predict_steps(i, end, times):
                    i = end
                else:  # the compiled path does not apply to this filter: step by step
                    break
        for k in range(i, len(times)):
            self._replay_step(k, times, twist_of, t_from)

    def _predict_steps(self, i0: int, i1: int, times: list[int]) -> bool:
        """Steps ``i0..i1-1`` (no measurement inside) by one :meth:`PoseUKF.predict_run`
        call, their snapshots kept; False (nothing done) where it does not apply."""
        run = range(i0, i1)
        states = self.filter.predict_run([self._twists[k] for k in run],
                                         [(times[k] - times[k - 1]) * 1e-6 for k in run])
        if states is None:
            return False
        for n, snap in enumerate(self._run_snapshots(states)):
            self._snaps[i0 + n] = snap
        return True

    def _run_snapshots(self, states: tuple[Tensor, Tensor, Tensor]) -> list[tuple[Tensor, ...]]:
        """The snapshots of the steps of a :meth:`PoseUKF.predict_run` (its states ``t``,
        ``q``, ``cov``, one per step; the last is the filter's now): the other state tensors
        (counters) are unchanged by a predict and shared with the final snapshot."""
        last = self._snapshot()  # the final state, and the unchanged counters' copies
        slots = self._run_slots
        return [*(_RunStepSnapshot(states, i, last, slots) for i in range(len(states[0]) - 1)),
                last]

    def step_run(self, times: Sequence[int], twists: Tensor
                 ) -> tuple[Tensor, Tensor, Tensor] | None:
        """:meth:`step` to each of ``times`` (µs, rising, after :attr:`now`) with the twist
        ``twists[k]`` (1,6) in one compiled call (:meth:`PoseUKF.predict_run
        <evtrack.filters.PoseUKF.predict_run>`): the same states and snapshots, bit for bit.
        For a tracker's run of velocity steps without a measurement.

        Args:
            times: (n,) step ends. twists: (n,1,6).

        Returns:
            The states after each step, ``t`` (n,1,3), ``q`` (n,1,4), ``cov`` (n,1,6,6) (not
            to be changed: the snapshots share them); ``None``, with nothing done, where the
            compiled path does not apply (a :class:`PoseTwistUKF`, a batch, CUDA, float32...):
            then call :meth:`step` per step.
        """
        ends = [int(t) for t in times]
        if len(ends) != len(twists):
            raise ValueError(f"PoseTimeline.step_run: {len(ends)} times but {len(twists)} twists")
        if not ends or not self.twist_driven:
            return None
        starts = [self.now, *ends[:-1]]
        if any(b <= a for a, b in zip(starts, ends, strict=True)):
            raise ValueError(f"PoseTimeline.step_run: times must rise after {self.now} µs, "
                             f"got {ends}")
        steps = list(twists.clone().unbind(0))  # kept: not the caller's to change
        states = self.filter.predict_run(steps, [(b - a) * 1e-6 for a, b in
                                                 zip(starts, ends, strict=True)])
        if states is None:
            return None
        self._times.extend(ends)
        self._snaps.extend(self._run_snapshots(states))
        self._twists.extend(steps)
        self._trim()
        return states

    def _replay_step(self, i: int, times: list[int],
                     twist_of: Callable[[int, int], Tensor | None] | None, t_from: int) -> None:
        """Redo step ``i`` of :meth:`_replay`."""
        t_start, t_end = times[i - 1], times[i]
        if (twist_of is not None and t_start >= t_from
                and bool(self.filter.initialized[0])):
            new = twist_of(t_start, t_end)
            if new is not None:
                self._twists[i] = new.clone()
        twist = self._twists[i]
        t_cur = t_start
        for r in self._records:
            if t_start < r.t_us <= t_end:
                self._predict(r.t_us - t_cur, twist)
                self._fuse(r)
                t_cur = r.t_us
        self._predict(t_end - t_cur, twist)
        self._snaps[i] = self._snapshot()

    def remeasure(self, t_us: int, twist_of: Callable[[int, int], Tensor | None]) -> int:
        """Measure again the twists of the kept steps after ``t_us``, and replay them.

        For a twist-driven filter whose twists were measured without a pose (before the first
        one, or after losing the object): once a late pose for ``t_us`` has started the track,
        the motion of the steps since can be measured again at the poses the filter now has.
        The kept steps from the one holding ``t_us`` on are redone in time order; before each
        that starts at or after ``t_us``, ``twist_of(t_start, t_end)`` is called with the
        filter holding the state at ``t_start`` (every kept measurement up to then fused) and
        returns the step's new twist (1, 6), or ``None`` to keep the old one. Steps when the
        filter holds no pose keep their twists and are not asked for. The state at
        :attr:`now` is the result.

        Returns:
            The number of steps asked for a twist.

        Raises:
            ValueError: the filter is not twist-driven, or ``t_us`` is outside the kept past.
        """
        if not self.twist_driven:
            raise ValueError("PoseTimeline.remeasure needs a twist-driven filter (PoseUKF)")
        t_us = int(t_us)
        times = list(self._times)
        if t_us < times[0] or t_us > self.now:
            raise ValueError(f"remeasure: {t_us} µs is outside the kept past "
                             f"[{times[0]}, {self.now}] µs")
        j = max(bisect.bisect_left(times, t_us) - 1, 0)
        self._restore(self._snaps[j])
        asked = 0

        def counted(t_start: int, t_end: int) -> Tensor | None:
            nonlocal asked
            asked += 1
            return twist_of(t_start, t_end)

        self._replay(j, times, counted, t_us)
        return asked

    def pose_at(self, t_us: int) -> tuple[Tensor, Tensor] | None:
        """``(t (3,), q (4,))`` the filter had at a kept past time ``t_us`` <= :attr:`now`:
        the state after the last step ending at or before it, predicted to ``t_us`` (with
        that step's twist for a twist-driven filter); measurements inside that step are not
        applied. ``None`` outside the kept past or when the filter had no pose then. The
        current state is left as it was."""
        t_us = int(t_us)
        times = self._times
        if t_us < times[0] or t_us > self.now:
            return None
        j = bisect.bisect_right(list(times), t_us) - 1
        state = dict(zip(self.names, self._snaps[j], strict=True))
        if "initialized" in state and not bool(state["initialized"][0]):
            return None
        if t_us == times[j]:
            return state["t"][0].clone(), state["q"][0].clone()
        current = self._snapshot()
        try:
            self._restore(self._snaps[j])
            self._predict(t_us - times[j], self._twists[j + 1])
            return self.filter.t[0].clone(), self.filter.q[0].clone()
        finally:
            self._restore(current)

    def pose_at_now(self) -> tuple[Tensor, Tensor]:
        """``(t (3,), q (4,))`` of the current state."""
        return self.filter.t[0], self.filter.q[0]


def pose_measurement_value(T: Tensor, dtype: torch.dtype, device: torch.device
                           ) -> tuple[Tensor, Tensor]:
    """(4, 4) pose -> ``(t (1,3), q (1,4))`` for :meth:`PoseTimeline.add`."""
    from evtrack.geometry import matrix_to_tq

    t, q = matrix_to_tq(T.to(torch.float64))
    return t.reshape(1, 3).to(dtype=dtype, device=device), q.reshape(1, 4).to(dtype=dtype,
                                                                              device=device)
