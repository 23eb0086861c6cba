"""Measuring again the velocity steps taken before the first pose (``remeasure.on_pose``).

Before the first pose the flow runs on all events (no silhouette), so that a late first pose
is carried to the present by the measured motion. Those steps' RoI flows are kept; once the
pose is there, they are measured again, each at the pose the filter has at its start (RoIs
inside the silhouette, depths in its range, the object's centre as the velocity filter's
pivot), and the pose filter is replayed with these twists. A pose that does not explain the
kept events (fewer than ``remeasure.min_inside`` of them inside its silhouette) is not used
for it: measured again at a wrong pose, the steps lose their RoIs and take depths out of the
object's range, which carries the wrong pose further off than the unposed twists do.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from itertools import groupby
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.filters import VelocityKF
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_timeline import PoseTimeline
from evtrack.tracking.roi_depth import DepthSnapshot, RoiDepth
from evtrack.tracking.silhouette import Silhouette, SilhouettePolygon
from evtrack.tracking.stats import StageTimer, TrackerStats
from evtrack.tracking.step_flows import SEGMENT_STEPS, StepFlows

__all__ = ["Remeasurer", "UnposedStep"]

CHECK_US = 50_000
"""µs after a late first pose whose kept RoI flows must lie in its silhouette."""
CHECK_MODEL_ROIS = 20
"""With model depth the unposed steps only predict: the timeline holds the late pose still
over them, so only the earliest RoI flows after it are checked (whole steps in time order,
until at least this many), which a moving object's events have not yet left."""
CHECK_MIN_ROIS = 10
"""Fewer RoI flows than this in that span: no check."""
CHECK_MIN_SUPPORT = 5
"""Only RoI flows of at least this many supporting events count in the check: the weakly
supported ones (the tracker reports windows from ``flow.min_support`` 2) include a few from
sensor noise off the object, 8 of 297 on the tests' small box against none of the
well-supported 90, which a right pose cannot explain."""


@dataclass
class UnposedStep:
    """A velocity step measured without a pose (all events, no silhouette): its RoI flows and
    the sensor depth frame of that time."""

    uv: np.ndarray  # (N, 2) float64 px
    flow: Tensor  # (N, 2) px/s
    normal: Tensor  # (N,) bool
    depth: DepthSnapshot | None  # (map, t_us) of the sensor depth, None for model depth
    support: np.ndarray  # (N,) events with candidates in each RoI window


class Remeasurer:
    """Keeps the unposed steps and measures them again once a late pose starts the track.

    Args:
        config: the tracker's config.
        vkf: the velocity filter.
        timeline: the pose filter's timeline.
        depth: the RoI depth.
        silhouette: the object's silhouette in the event camera.
        segment_pose: ``() -> (pose (4, 4), silhouette or None)`` of a new segment of a step
            group at the filter's present pose (sets the velocity filter's pivot).
        past_pose: ``t_us -> (4, 4) or None``, the filter's pose at a kept past time.

    Attributes:
        stats: the counters it adds to (``steps_remeasured``, ``remeasures_skipped``).
        unposed: the kept steps by end time (µs), in time order.
    """

    def __init__(self, config: TrackerConfig, vkf: VelocityKF, timeline: PoseTimeline,
                 depth: RoiDepth, silhouette: Silhouette,
                 segment_pose: Callable[[], tuple[np.ndarray, SilhouettePolygon | None]],
                 past_pose: Callable[[int], np.ndarray | None]) -> None:
        self.config = config
        self.vkf = vkf
        self.timeline = timeline
        self.depth = depth
        self.silhouette = silhouette
        self.segment_pose = segment_pose
        self.past_pose = past_pose
        self.stats = TrackerStats()
        self.unposed: dict[int, UnposedStep] = {}
        self.keeping = True
        """Keep the unposed steps (:meth:`keep`). A :class:`~evtrack.tracking.multi.MultiTracker`
        turns it off for the trackers whose objects wait for their first pose behind another
        one's, which keeps the steps for all of them (:attr:`unposed` is then that one's)."""
        self.check_events = True
        """Check that the late pose explains the kept events (:meth:`explains_events`) before
        measuring them again. :class:`~evtrack.tracking.multi.MultiTracker` turns it off:
        before its objects' first poses nobody owns an event, so every tracker keeps the
        flows of all objects, which no one pose explains; measured again, each keeps those
        inside its own silhouette."""

    def keep(self, t_end: int, flows: StepFlows, k: int) -> None:
        """Keep step ``k`` (ending at ``t_end``) of an unposed group, and forget the kept steps
        older than the pose filter's past (nothing while not :attr:`keeping`)."""
        if not self.keeping:
            return
        uv, flow, normal = flows.step(k)
        depth = self.depth.snapshot()
        lo, hi = int(flows.bounds[k]), int(flows.bounds[k + 1])
        self.unposed[t_end] = UnposedStep(uv, flow, normal, depth, flows.support[lo:hi])
        oldest = t_end - self.timeline.horizon_us
        while self.unposed and next(iter(self.unposed)) <= oldest:
            del self.unposed[next(iter(self.unposed))]

    def remeasure(self, t_pose: int, step_runs: bool) -> None:
        """The late pose of ``t_pose`` started the track: measure the kept steps after it
        again, with the velocity filter started afresh at ``t_pose``, one pose per segment of
        a step group as the live steps have, and replay the pose filter with these twists.
        ``step_runs``: the velocity filter's compiled runs where they apply."""
        kept, self.unposed = self.unposed, {}
        cfg = self.config
        if self.check_events and not self.explains_events(t_pose, kept):
            self.stats.remeasures_skipped += 1
            return
        self.vkf.reset(1)
        saved = self.depth.snapshot()
        group_us = cfg.velocity_step_us * cfg.flow_batch_steps
        segment_us = cfg.velocity_step_us * min(SEGMENT_STEPS, cfg.flow_batch_steps)

        def segment(t_us: int) -> tuple[int, int]:  # (group, segment within it) of a step
            return t_us // group_us, t_us % group_us // segment_us

        at: dict[str, Any] = {"segment": None, "twists": {}}

        def twist_of(t_start: int, t_end: int) -> Tensor:
            if at["segment"] != segment(t_start):
                pose, poly = self.segment_pose()
                at["segment"] = segment(t_start)
                # the segment's steps from here on (those starting before the next segment's),
                # all asked in turn: the filter holds a pose
                group_end = min((t_start // group_us + 1) * group_us,
                                t_start // group_us * group_us
                                + (segment(t_start)[1] + 1) * segment_us)
                times = [t_start]
                for t in self.timeline.step_ends(t_start, self.timeline.now):
                    if times[-1] >= group_end:
                        break
                    times.append(t)
                at["twists"] = self._group(kept, times, poly, pose, step_runs)
            twist = at["twists"].pop(t_end, None)
            if twist is None:
                raise RuntimeError(f"remeasure: step ({t_start}, {t_end}] µs was not among "
                                   "its group's steps")
            return twist

        self.depth.invalidate_model()  # rendered again at the replayed poses and times
        try:
            with StageTimer(self.stats.time_s, "velocity"):
                self.timeline.remeasure(t_pose, twist_of)
        finally:
            if saved is not None:
                self.depth.restore(saved)
            else:
                self.depth.invalidate_model()  # the live steps render at the present pose

    def _group(self, kept: dict[int, UnposedStep], times: list[int],
               poly: SilhouettePolygon | None, pose: np.ndarray, step_runs: bool
               ) -> dict[int, Tensor]:
        """The new twists (1, 6) of the steps ``(times[i], times[i + 1]]`` of one segment, by
        step end: the kept RoIs inside the segment's silhouette, their depths at its pose
        from each step's depth frame, then the velocity filter, by one compiled run where it
        applies (:meth:`VelocityKF.forward_run <evtrack.filters.VelocityKF.forward_run>`) or
        step by step: the same twists either way. A step without RoIs inside only predicts."""
        cfg = self.config
        n = len(times) - 1
        dts = [(times[i + 1] - times[i]) * 1e-6 for i in range(n)]
        steps = [kept.get(t_end) for t_end in times[1:]]
        uv, flow, normal = self._inside(steps, poly)
        z = self._depths(steps, times, uv, poly, pose)
        measured = [i for i in range(n) if len(uv[i])]
        self.stats.steps_remeasured += len(measured)
        twists: list[Tensor] = []
        if measured and step_runs:
            bounds = np.concatenate([[0], np.cumsum([len(u) for u in uv])])
            run = self.vkf.forward_run(
                dts, bounds, torch.from_numpy(np.concatenate(uv)),
                torch.from_numpy(np.concatenate(z)), torch.cat([flow[i] for i in measured]),
                torch.cat([normal[i] for i in measured]) if cfg.use_flow_normal_flags else None)
            if run is not None:
                twists = list(run.unbind(0))
        for i in range(len(twists), n):  # step by step (the rest after a failed run)
            if len(uv[i]):
                twists.append(self.vkf_update(dts[i], uv[i], z[i], flow[i], normal[i]))
            else:
                twists.append(self.vkf.predict(dts[i]))
        return dict(zip(times[1:], twists, strict=True))

    def vkf_update(self, dt: float, uv: np.ndarray, z: np.ndarray, flow: Tensor,
                   normal: Tensor) -> Tensor:
        """One velocity-filter predict + update from (N,) RoIs; returns the twist (1, 6)."""
        kw = {"dtype": self.vkf.twist.dtype, "device": self.vkf.twist.device}
        return self.vkf(dt, torch.as_tensor(uv, **kw).unsqueeze(0),
                        torch.as_tensor(z, **kw).unsqueeze(0), flow.unsqueeze(0),
                        normal.unsqueeze(0) if self.config.use_flow_normal_flags else None)

    def _inside(self, steps: list[UnposedStep | None], poly: SilhouettePolygon | None
                ) -> tuple[list[np.ndarray], list[Tensor | None], list[Tensor | None]]:
        """Each step's RoIs inside ``poly`` (with the mask margin): centres, flows, normal
        flags; one silhouette test for all of them."""
        n = len(steps)
        rows = ([i for i, step in enumerate(steps) if step is not None and len(step.uv)]
                if poly is not None else [])
        uv: list[np.ndarray] = [np.zeros((0, 2))] * n
        flow: list[Tensor | None] = [None] * n
        normal: list[Tensor | None] = [None] * n
        if not rows:
            return uv, flow, normal
        inside = np.split(poly.contains(np.concatenate([steps[i].uv for i in rows]),
                                        self.config.mask_margin_px),
                          np.cumsum([len(steps[i].uv) for i in rows])[:-1])
        for i, keep in zip(rows, inside, strict=True):
            if keep.any():
                step = steps[i]
                uv[i] = step.uv[keep]
                sel = torch.from_numpy(keep)
                flow[i] = step.flow[sel.to(step.flow.device)]
                normal[i] = step.normal[sel.to(step.normal.device)]
        return uv, flow, normal

    def _depths(self, steps: list[UnposedStep | None], times: list[int],
                uv: list[np.ndarray], poly: SilhouettePolygon | None,
                pose: np.ndarray) -> list[np.ndarray]:
        """The depths (m) of the RoIs ``uv[i]``, each read from its own step's sensor depth
        frame at the step's start (rendered at the segment's pose for model depth), missing
        ones by the fallback (counted): one lookup per run of steps reading the same frame,
        the same depths as one per step."""
        z = [np.zeros(0)] * len(uv)
        measured = [i for i in range(len(uv)) if len(uv[i])]
        sensor = self.depth.sensor
        max_age_us = self.depth.max_age_us

        def frame(i: int) -> tuple[Any, ...]:
            if not sensor:
                return (i,)  # model depth: rendered per step
            depth_map, t_us = steps[i].depth
            stale = t_us is not None and times[i] - t_us > max_age_us
            return (id(depth_map), t_us, stale)

        for _, same_frame in groupby(measured, key=frame):
            run = list(same_frame)
            if sensor:
                self.depth.restore(steps[run[0]].depth)
            both = self.depth.lookup(np.concatenate([uv[i] for i in run]), poly, pose,
                                     t_now=times[run[0]])
            for i, part in zip(run, np.split(both, np.cumsum([len(uv[i]) for i in run])[:-1]),
                               strict=True):
                z[i] = part
        return z

    def explains_events(self, t_pose: int, kept: dict[int, UnposedStep]) -> bool:
        """Whether at least ``remeasure.min_inside`` of the kept RoI flows (of at least
        ``CHECK_MIN_SUPPORT`` supporting events) of the ``CHECK_US`` after ``t_pose`` lie in
        the silhouette (with the mask margin) at the timeline's pose of their step (carried
        from the pose by the unposed twists; with model depth, held still: only the steps up
        to the first ``CHECK_MODEL_ROIS`` such RoI flows); True when they are fewer than
        ``CHECK_MIN_ROIS``."""
        inside = total = 0
        held_still = not self.depth.sensor
        for t_end, step in kept.items():  # in time order (kept as the steps ran)
            if not t_pose < t_end <= t_pose + CHECK_US or not len(step.uv):
                continue
            if held_still and total >= CHECK_MODEL_ROIS:
                break
            pose = self.past_pose(t_end)
            if pose is None:
                continue
            uv = step.uv[step.support >= CHECK_MIN_SUPPORT]
            poly = self.silhouette.polygon(pose) if np.isfinite(pose).all() else None
            total += len(uv)
            if poly is not None and len(uv):
                inside += int(poly.contains(uv, self.config.mask_margin_px).sum())
        if total < CHECK_MIN_ROIS:
            return True
        return inside / total >= self.config.remeasure.min_inside
