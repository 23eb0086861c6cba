"""The event motion source of the ``full`` and ``velocity`` methods: the event optical flow
(:class:`~evtrack.flow.TripletFlow`, one call per step group) and the velocity filter
(:class:`~evtrack.filters.VelocityKF`, one update per velocity step from the step's RoI flows
and their depths).

Event bursts (:mod:`evtrack.tracking.event_gate`) take the burst steps' events out; after one,
the flow's burst filter is re-synchronised: each pixel's first event after it would start a
burst even in the middle of an edge's, and these onsets, nearly simultaneous along the edges,
pair into spurious fast flows (a 20 ms burst on a 128x96 sequence: ω_z of -24 to -38 rad/s for
a few ms after it). For ``flow.refractory_us`` after the burst, the span in which a taken-out
event could still hold back a later one, the first event of each pixel is taken as the
continuation of a burst (:meth:`TripletFlow.continue_bursts
<evtrack.flow.TripletFlow.continue_bursts>`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evtrack.events import Events
from evtrack.filters import VelocityKF
from evtrack.flow import FlowResult, TripletFlow
from evtrack.tracking.motion.base import MotionContext, MotionServices, MotionSource, StepRun
from evtrack.tracking.remeasure import Remeasurer
from evtrack.tracking.silhouette import SilhouettePolygon
from evtrack.tracking.stats import StageTimer
from evtrack.tracking.step_flows import StepFlows

__all__ = ["EventMotion", "VelocityOnlyMotion"]


class EventMotion(MotionSource):
    """Event flow + velocity filter, poses fused by the pose filter (``method: full``).

    Before the first pose the flow runs on all events (``remeasure.before_pose``), so that a
    late first pose is carried to the present by the measured motion (with sensor depth also
    measured then; model depth needs the pose), and those steps are measured again once that
    pose is there (``remeasure.on_pose``, :mod:`evtrack.tracking.remeasure`).

    Attributes:
        flow: the event optical flow.
        vkf: the velocity filter.
    """

    uses_events = True

    def __init__(self, context: MotionContext) -> None:
        super().__init__(context)
        cfg = self.config
        camera = context.camera
        self.flow = TripletFlow(cfg.flow.replace(sensor_size=camera.size, device=cfg.device))
        self.vkf = VelocityKF(camera, 1, cfg.velocity_kf, device=self.device)
        self.vkf.prepare_pixels(self.flow.roi_centres())  # a distorted camera's RoIs: once
        vertices = np.asarray(context.vertices, np.float64).reshape(-1, 3)
        self.object_radius_m = (float(np.linalg.norm(vertices, axis=1).max())
                                if len(vertices) else 0.0)  # m
        self.events_before_pose = cfg.remeasure.before_pose
        self.remeasurer: Remeasurer | None = None
        self.flows: StepFlows | None = None
        self._resync: tuple[int, int] | None = None
        self._resync_seen = np.zeros(0, bool)

    def bind(self, services: MotionServices) -> None:
        super().bind(services)
        if self.events_before_pose and self.config.remeasure.on_pose:
            self.remeasurer = Remeasurer(self.config, self.vkf, services.timeline,
                                         services.depth, self.context.silhouette,
                                         services.segment_pose, services.past_pose)

    # ------------------------------------------------------------ state
    def reset(self) -> None:
        self.flow.reset()
        self.vkf.reset(1)
        self.flows = None
        self._resync = None  # µs: a flow re-sync going on
        self._resync_seen = np.zeros(0, bool)  # pixels with an event in that re-sync so far
        if self.remeasurer is not None:
            self.remeasurer.unposed = {}
            self.remeasurer.stats = self.stats

    def lost(self) -> None:
        self.vkf.reset(1)

    def twist(self) -> np.ndarray:
        return np.array(self.vkf.twist.tolist()[0], np.float64)

    def segment_started(self, pose: np.ndarray | None) -> None:
        """The velocity filter's pivot (object-centred process noise): the object's centre at
        ``pose``; none without a finite pose, or for a scene around the camera
        (:meth:`is_scene_at`)."""
        if self.config.velocity_kf.object_centred:
            self.vkf.set_pivot(None if pose is None or not np.isfinite(pose).all()
                               or self.is_scene_at(pose)
                               else torch.from_numpy(np.ascontiguousarray(pose[:3, 3])))

    def is_scene_at(self, pose: np.ndarray) -> bool:
        """Whether the object at ``pose`` (4, 4) is a scene around the camera rather than an
        object before it: its radius (its farthest vertex from its origin) at least
        ``pivot_max_radius_ratio`` times its origin's distance. What moves is then the
        camera, which turns about itself, not about the scene's origin."""
        distance = float(np.linalg.norm(pose[:3, 3]))
        return self.object_radius_m >= self.config.pivot_max_radius_ratio * distance

    def track_started(self, t_pose: int) -> None:
        if self.remeasurer is not None and self.remeasurer.unposed:
            self.remeasurer.remeasure(t_pose, self.services.step_runs())

    # ------------------------------------------------------------ steps
    def begin_group(self, ev: Events, t0: int, t_end: int, pose: np.ndarray | None,
                    search_budget: int) -> None:
        cfg = self.config
        step = cfg.velocity_step_us
        self.segment_started(pose)  # the segment's pose: one pivot for its steps
        with StageTimer(self.stats.time_s, "flow"):
            # group ends are whole steps, and steps whole flow windows (the config checks it):
            # every window of the group is over, one registration reports all
            fc = self.flow.config
            search = self.services.gate.search_sample(ev, self.flow.events_seen,
                                                      cfg.load.search_per_roi_window, search_budget,
                                                      fc.window_us)
            self.flows = StepFlows(self._flow_update(ev, t_end, search), t0, step,
                                   (t_end - t0) // step, self.vkf.twist.dtype, self.device)

    def _flow_update(self, ev: Events, t_end: int, search: Tensor | None) -> FlowResult:
        """The flow of a step group's events (its windows all end by ``t_end``), the flow's
        burst filter re-synchronised after each burst (see the module docstring)."""
        span = self.flow.config.refractory_us
        carried = self._resync is not None
        windows = [self._resync] if carried else []
        windows += [(end, end + span) for end in self.services.gate.burst_ends] if span else []
        self._resync = None
        camera = self.context.camera
        parts, pos = [], 0
        for i, (start, end) in enumerate(windows):
            if i + 1 < len(windows):  # a later burst ends it (its events are taken out)
                end = min(end, windows[i + 1][0])
            if not (i == 0 and carried):  # a new re-sync: no pixel seen yet
                self._resync_seen = np.zeros(camera.width * camera.height, bool)
            if start >= t_end:  # a burst ending the group: the next group's
                self._resync = (start, end)
                break
            cut = max(pos, int(torch.searchsorted(ev.t, start))) if len(ev) else 0
            if cut > pos:
                parts.append(self.flow.update(ev[pos:cut], until_us=start, search=None
                                              if search is None else search[pos:cut]))
                pos = cut
            hi = int(torch.searchsorted(ev.t, min(end, t_end))) if len(ev) else 0
            pixel = (ev.y[cut:hi].long() * camera.width + ev.x[cut:hi].long()).numpy()
            first = np.unique(pixel, return_index=True)[1]  # each pixel's first event
            first = np.sort(first[~self._resync_seen[pixel[first]]])
            self._resync_seen[pixel] = True
            self.flow.continue_bursts(ev[cut:hi][torch.from_numpy(first)])
            if end > t_end:
                self._resync = (start, end)
        parts.append(self.flow.update(ev[pos:], until_us=t_end,
                                      search=None if search is None else search[pos:]))
        return parts[0] if len(parts) == 1 else FlowResult.cat(parts)

    def step(self, k: int, dt: float, pose: np.ndarray | None,
             poly: SilhouettePolygon | None, usable: bool) -> Tensor:
        with StageTimer(self.stats.time_s, "velocity"):
            if usable:
                return self._velocity_step(dt, k, poly, pose)
            return self.vkf.predict(dt)

    def keep_unposed(self, k: int, t_end: int) -> None:
        if self.remeasurer is not None:
            self.remeasurer.keep(t_end, self.flows, k)

    def _velocity_step(self, dt: float, k: int, poly: SilhouettePolygon | None,
                       pose: np.ndarray | None) -> Tensor:
        """Velocity-filter predict + update from the RoI flows of step ``k`` of the group;
        returns the twist (1, 6)."""
        flows = self.flows
        depth = self.services.depth
        uv, flow, normal = flows.step(k)
        if len(uv) == 0 or (poly is None and pose is not None):
            return self.vkf.predict(dt)
        t_now = self.services.now()
        if pose is None:  # before the first pose: plain patch medians, no fallback
            if not depth.sensor:
                return self.vkf.predict(dt)  # model depth needs a pose (see remeasure)
            z = depth.unranged(uv, t_now)
        elif depth.sensor:
            z = depth.step(flows, k, poly, pose, t_now)
        else:
            z = depth.lookup(uv, poly, pose, t_now)
        self.stats.roi_flows += len(uv)
        self.stats.velocity_updates += 1
        kw = {"dtype": self.vkf.twist.dtype, "device": self.device}
        return self.vkf(dt, torch.as_tensor(uv, **kw).unsqueeze(0),
                        torch.as_tensor(z, **kw).unsqueeze(0), flow.unsqueeze(0),
                        normal.unsqueeze(0) if self.config.use_flow_normal_flags else None)

    @property
    def has_step_runs(self) -> bool:
        return self.flows is not None and self.services.depth.sensor

    def run_twists(self, k: int, end: int, pose: np.ndarray, poly: SilhouettePolygon
                   ) -> StepRun | None:
        """Steps ``k..end-1`` with the velocity filter's compiled run
        (:meth:`VelocityKF.forward_run <evtrack.filters.VelocityKF.forward_run>`): the same
        twists as step by step."""
        flows = self.flows
        step = self.config.velocity_step_us
        with StageTimer(self.stats.time_s, "velocity"):
            bounds = flows.bounds[k:end + 1]
            lo, hi = int(bounds[0]), int(bounds[-1])
            z, missing = self.services.depth.run(flows, k, end, poly, pose, self.services.now())
            normal = flows.normal[lo:hi]
            twists = self.vkf.forward_run(
                [step * 1e-6] * (end - k), bounds - lo, torch.from_numpy(flows.uv[lo:bounds[-1]]),
                torch.from_numpy(z), flows.flow[lo:hi],
                normal if self.config.use_flow_normal_flags else None)
        if twists is None:
            return None
        return StepRun(twists, bounds - lo, missing)


class VelocityOnlyMotion(EventMotion):
    """The ``velocity`` baseline: the same velocity pipeline; poses are used only to initialise
    (and to re-initialise after the object was lost)."""

    poses_only_initialise = True
