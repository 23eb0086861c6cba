"""The step scheduler: the stream cut into step groups (``flow_batch_steps`` velocity steps, one
motion-source call each) and each group's velocity steps run through the filters, one by one
or, between two events of the stream (a frame, a measurement due, a depth map expiring), in
the filters' compiled runs.

Time: one clock in µs, advanced by the events (a step ``[t_k, t_k + step)`` closes when an event
at or after its end arrives) and by :meth:`Tracker.advance <evtrack.Tracker.advance>` /
:meth:`Tracker.push_frame <evtrack.Tracker.push_frame>`. The tracker outputs a pose and a twist
at the end of every step.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from evtrack.events import Events, concatenate
from evtrack.tracking.silhouette import SilhouettePolygon
from evtrack.tracking.stats import StageTimer
from evtrack.tracking.step_flows import SEGMENT_STEPS

if TYPE_CHECKING:
    from evtrack.tracking.tracker import Tracker

__all__ = ["MIN_RUN_STEPS", "StepScheduler", "group_spans", "quiet_end"]

MIN_RUN_STEPS = 2
"""The fewest velocity steps between two events of the stream that go through the filters'
compiled runs."""


def group_spans(start: int, end: int, group_us: int) -> list[tuple[int, int]]:
    """The step groups ``[g0, g1)`` (µs) covering ``[start, end)``: cut at the multiples of
    ``group_us``, the last one possibly short."""
    spans = []
    g_start = start
    while g_start < end:
        g_end = min((g_start // group_us + 1) * group_us, end)
        spans.append((g_start, g_end))
        g_start = g_end
    return spans


def quiet_end(t0: int, k: int, n_steps: int, step_us: int, next_frame_us: int | None,
              next_due_us: int | None, depth_expires_us: float | None) -> int:
    """The end (exclusive) of the steps from ``k`` of the group starting at ``t0`` that nothing
    falls between: no queued frame (earliest at ``next_frame_us``) is due before one of them,
    no pending measurement (earliest available at ``next_due_us``) is due at its end, and the
    sensor depth map (readable until ``depth_expires_us``) does not expire at its start (the
    steps' depths are one lookup). ``None``: nothing of that kind."""
    end = n_steps
    if next_frame_us is not None:  # frames before b_j are taken at the start of step j > k
        end = min(end, max(k + 1, (next_frame_us - t0) // step_us))
    if next_due_us is not None:  # due at b_j = t0 + (j + 1) step when available <= b_j
        end = min(end, (next_due_us - t0 - 1) // step_us)
    if depth_expires_us is not None:
        # step j reads the map at its start t0 + j step, expired beyond the maximum age
        end = min(end, math.floor((depth_expires_us - t0) / step_us) + 1)
    return end


class StepScheduler:
    """Runs the tracker's step groups (an internal part of :class:`~evtrack.Tracker`: it reads
    and moves the tracker's clock, queues and parts).

    Attributes:
        runs_declined: the filters' compiled runs did not apply once: not tried again.
    """

    def __init__(self, tracker: Tracker) -> None:
        self.tracker = tracker
        self.reset()

    def reset(self) -> None:
        """Forget the buffered events."""
        self.buffer: list[Events] = []
        self.runs_declined = False

    def advance(self, t_us: int, whole_groups: bool) -> None:
        """Close the step groups ending at or before ``t_us`` (``whole_groups=False``: every
        step, also inside an unfinished group)."""
        tr = self.tracker
        cfg = tr.config
        step = cfg.velocity_step_us
        group = step * cfg.flow_batch_steps
        end = (t_us // group) * group if whole_groups else (t_us // step) * step
        if end <= tr.stream.now:
            return
        buf = self.buffer
        ev = concatenate(buf) if len(buf) > 1 else (
            buf[0] if buf else Events.empty(tr.camera.size))
        try:
            for g_start, g_end in group_spans(tr.stream.now, end, group):
                k = int(torch.searchsorted(ev.t, torch.tensor([g_end]))[0]) if len(ev) else 0
                group_ev, ev = ev[:k], ev[k:]
                self.run_group(g_start, g_end, group_ev)
        finally:
            # also when a step raised (e.g. a frame read lazily that failed its checks): the
            # interrupted group's events are spent, so the stream goes on from the next group
            # (the rest of that group gets no flow) instead of failing on every later call
            self.buffer = [ev] if len(ev) else []

    def run_group(self, t0: int, t_end: int, ev: Events) -> None:
        """The step group ``[t0, t_end)`` (µs) with its events ``ev``: every step through the
        filters, its processing time given to the load controller (``load.realtime``)."""
        tr = self.tracker
        timed = bool(tr.config.load.realtime)
        started = tr.clock() if timed else 0.0
        self._group_steps(t0, t_end, ev)
        if timed:
            tr._budgets_after_group(tr.clock() - started, (t_end - t0) * 1e-6)

    def _gate(self, ev: Events, t0: int, t_end: int, pose: np.ndarray | None,
              poly: SilhouettePolygon | None) -> Events:
        """The group's events that reach an event-based motion source."""
        tr = self.tracker
        step = tr.config.velocity_step_us
        motion = tr.motion
        if poly is not None and len(ev):
            ev = tr.gate.on_object(ev, t0, t_end, step, pose, poly, motion.twist)
        elif not (pose is None and motion.events_before_pose):
            ev = ev[:0]
        n_steps = (t_end - t0) // step
        tr.load.observe_events(len(ev) / n_steps)
        return tr.gate.thin(ev, tr.load.budgets.events * n_steps)

    def _group_steps(self, t0: int, t_end: int, ev: Events) -> None:
        """Process the steps of ``[t0, t_end)``: one motion-source call for all of them (the
        mask is the silhouette predicted at ``t0``), then the filters step by step or in
        compiled runs."""
        tr = self.tracker
        st = tr.stats
        motion = tr.motion
        step = tr.config.velocity_step_us
        n_steps = (t_end - t0) // step
        tr.frames.due(t0 + step)
        pose = tr._present_pose() if tr.initialized else None
        poly = tr.silhouette.polygon(pose) if pose is not None else None
        if pose is not None:
            tr._pose_depth_uncertainty()
        tr.gate.burst_ends = []
        if motion.uses_events:
            ev = self._gate(ev, t0, t_end, pose, poly)
        motion.begin_group(ev, t0, t_end, pose, tr.load.budgets.search * n_steps)
        runs = (motion.has_step_runs and tr.step_runs and not self.runs_declined
                and tr.timeline.twist_driven)
        twist_driven = tr.timeline.twist_driven
        k = 0
        while k < n_steps:
            b = t0 + (k + 1) * step
            if k:
                tr.frames.due(b)
            initialized = tr.initialized  # asked once a step (a tensor read): frames_due
            # may change it; nothing below does before the step's filters
            if k and k % SEGMENT_STEPS == 0 and initialized:
                # a new segment: the filter's pose now (also when the group started without
                # one: a pose that started the track inside the group)
                pose, poly = tr._segment_pose()
            if runs and initialized and pose is not None and poly is not None:
                end = min(self._quiet_end(t0, k, n_steps),
                          (k // SEGMENT_STEPS + 1) * SEGMENT_STEPS)
                if end - k >= MIN_RUN_STEPS:
                    done = self.step_run(t0, k, end, poly, pose)
                    if done is None:  # the filters' compiled paths do not apply
                        self.runs_declined, runs = True, False
                    elif done > k:
                        k = done
                        continue
            usable = pose is None or initialized  # lost inside the group: predict only
            twist = motion.step(k, step * 1e-6, pose, poly, usable)
            if pose is None:
                motion.keep_unposed(k, b)
            with StageTimer(st.time_s, "pose"):
                tr.timeline.step(b, twist if twist_driven else None)
                tr.stream.now = b
                tr.fusion.apply_due(b)
            st.steps += 1
            tr._check_view(b)
            tr._record(b)
            k += 1

    def _quiet_end(self, t0: int, k: int, n_steps: int) -> int:
        tr = self.tracker
        return quiet_end(t0, k, n_steps, tr.config.velocity_step_us, tr.frames.next_us,
                         tr.measurements.next_due_us, tr.roi_depth.expires_after_us())

    def step_run(self, t0: int, k: int, end: int, poly: SilhouettePolygon,
                  pose: np.ndarray) -> int | None:
        """Steps ``k..end-1`` of the group starting at ``t0`` (see :func:`quiet_end`) with the
        filters' compiled runs (the motion source's :meth:`run_twists
        <evtrack.tracking.motion.MotionSource.run_twists>`, :meth:`PoseTimeline.step_run
        <evtrack.tracking.pose_timeline.PoseTimeline.step_run>`): the same states, outputs and
        counts as step by step, a few calls instead of a few dozen per step.

        Returns:
            The next step to do: ``end``, or earlier when the object is lost at a step of the
            run (the steps after it are left to the step loop) or a velocity update needs the
            torch path (that step is left to it); ``None``, with nothing done, where the
            compiled runs do not apply.
        """
        tr = self.tracker
        run = tr.motion.run_twists(k, end, pose, poly)
        if run is None:
            return None
        twists = run.twists
        done = k + len(twists)
        if done == k:
            return k
        st = tr.stats
        step = tr.config.velocity_step_us
        with StageTimer(st.time_s, "pose"):
            ends = [t0 + (j + 1) * step for j in range(k, done)]
            tq = self._run_poses(ends, twists)
            # the steps whose silhouette is whole in view (the view check's common case:
            # visible 1.0, never below min_visible_fraction, which the config keeps in [0, 1])
            in_view = tr.silhouette.boxes_in_image(tq[:, :3], tq[:, 3:])
            lost = False
            for n, b in enumerate(ends):
                if in_view[n]:
                    tr.view.out_of_view_us = 0
                else:
                    tr.stream.now = b
                    if tr._check_view(b, tq[n, :3].tolist(), tq[n, 3:].tolist()):
                        lost = True  # the held pose is set; the later steps: the step loop
                        break
            m = n + 1  # the steps counted here; the last one lost when ``lost``
            tracked = m - 1 if lost else m
            tr.outputs.extend_tracking(ends[:tracked], tq[:tracked],
                                       twists[:tracked, 0].numpy().copy())
            per_step = np.diff(run.bounds[:m + 1])  # RoI flows of each step
            st.steps += m
            st.roi_flows += int(per_step.sum())
            st.velocity_updates += int(np.count_nonzero(per_step))
            st.depth_fallbacks += int(run.missing[:int(run.bounds[m])].sum())
            tr.stream.now = ends[m - 1]
            if lost:
                tr._record(ends[m - 1])
                return k + m
            tr._held = None  # tracking: no held pose
        return done

    def _run_poses(self, ends: list[int], twists: torch.Tensor) -> np.ndarray:
        """(M, 7) ``[t, q]`` of the pose filter after each step of a run (a new array)."""
        tr = self.tracker
        states = tr.timeline.step_run(ends, twists)
        if states is not None:
            return torch.cat([states[0][:, 0], states[1][:, 0]], 1).numpy()  # a new array
        # the pose filter's compiled run does not apply (sigma points...): per step
        rows_tq = []
        ukf = tr.timeline.filter
        for b, twist in zip(ends, twists, strict=True):
            tr.timeline.step(b, twist)
            rows_tq.append(ukf.t.tolist()[0] + ukf.q.tolist()[0])
        return np.array(rows_tq, np.float64).reshape(len(ends), 7)
