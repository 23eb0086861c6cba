"""The motion source interface: what measures the object's motion between poses.

A :class:`~evtrack.Tracker` holds one motion source, picked by ``TrackerConfig.method`` from the
registry (:mod:`evtrack.tracking.methods`). The tracker runs the clock, the event gate,
the pose filter and its measurements; the motion source turns each velocity step into a twist
for the pose filter (or, for a frame-based one, into twist measurements).

Per step group ``[t0, t_end)`` the tracker calls :meth:`MotionSource.begin_group` with the
group's gated events, then, for each velocity step ``k``, :meth:`MotionSource.step`, whose
twist (1, 6) ``[v_o, ω]`` (m/s, rad/s, event camera frame) drives the pose filter's predict.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.events import Events
from evtrack.filters import PoseTwistUKF, PoseUKF
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.silhouette import Silhouette, SilhouettePolygon
from evtrack.tracking.stats import TrackerStats

if TYPE_CHECKING:
    from evtrack.tracking.event_gate import EventGate
    from evtrack.tracking.inputs import Measurement
    from evtrack.tracking.pose_timeline import PoseTimeline
    from evtrack.tracking.roi_depth import RoiDepth

__all__ = ["MotionContext", "MotionServices", "MotionSource", "StepRun"]


@dataclass(frozen=True)
class MotionContext:
    """What a motion source is built from.

    Attributes:
        config: the tracker's config.
        camera: the event camera; rgb_camera: the RGB-D camera.
        T_event_rgb: (4, 4) float64, RGB-camera points into the event camera.
        device: of the filters.
        vertices: (V, 3) float64 the object's vertices (m).
        silhouette: the object's silhouette in the event camera.
        aligned: whether the RGB images are the event camera's (same camera, identity
            extrinsic).
    """

    config: TrackerConfig
    camera: PinholeCamera
    rgb_camera: PinholeCamera
    T_event_rgb: Tensor
    device: torch.device
    vertices: np.ndarray
    silhouette: Silhouette
    aligned: bool


@dataclass(frozen=True)
class MotionServices:
    """The tracker's parts a motion source may use once the tracker is built.

    Attributes:
        now: ``() -> µs``, the clock (end of the last closed velocity step).
        initialized: ``() -> bool``, whether the pose filter holds a pose.
        pose: ``t_us -> (4, 4)``, :meth:`evtrack.Tracker.pose`.
        past_pose: ``t_us -> (4, 4) or None``, the filter's pose at a kept past time.
        segment_pose: ``() -> (pose, silhouette or None)`` at the filter's present pose.
        schedule: ``(available_us, measurement)``: queue a measurement for the pose filter
            (applied once the clock reaches ``available_us``).
        step_runs: ``() -> bool``, whether the filters' compiled runs are wanted.
        timeline: the pose filter's timeline.
        depth: RoI depth.
        gate: the event gate.
    """

    now: Callable[[], int]
    initialized: Callable[[], bool]
    pose: Callable[[int], np.ndarray]
    past_pose: Callable[[int], np.ndarray | None]
    segment_pose: Callable[[], tuple[np.ndarray, SilhouettePolygon | None]]
    schedule: Callable[[int, Measurement], None]
    step_runs: Callable[[], bool]
    timeline: PoseTimeline
    depth: RoiDepth
    gate: EventGate


@dataclass
class StepRun:
    """The twists of a run of velocity steps measured in one compiled call
    (:meth:`MotionSource.run_twists`).

    Attributes:
        twists: (M, 1, 6) the steps' twists (M <= the steps asked for).
        bounds: (steps + 1,) the RoI flows of each step asked for: ``bounds[j]:bounds[j + 1]``
            relative to ``bounds[0]``.
        missing: which RoI depths took the fallback (rows from ``bounds[0]``).
    """

    twists: Tensor
    bounds: np.ndarray
    missing: np.ndarray


class MotionSource:
    """Base class of the motion sources (see the module docstring).

    Class attributes say how the tracker treats the method:

    Attributes:
        uses_events: the event gate runs and the group's events reach :meth:`begin_group`.
        uses_rgb: the RGB frames are read for :meth:`on_rgb`.
        poses_only_initialise: poses only start (or restart) the track.
        events_before_pose: events reach it before the first pose (else none until then).
        stats: the counters it adds to (set by the tracker at each reset).
    """

    uses_events: ClassVar[bool] = False
    uses_rgb: ClassVar[bool] = False
    poses_only_initialise: ClassVar[bool] = False

    def __init__(self, context: MotionContext) -> None:
        self.context = context
        self.config = context.config
        self.device = context.device
        self.stats = TrackerStats()
        self.services: MotionServices | None = None
        self.events_before_pose = False

    # ------------------------------------------------------------ wiring
    def sensing_camera(self) -> PinholeCamera:
        """The camera whose images measure the motion (its depth frames are used)."""
        return self.context.camera

    def sensing_silhouette(self) -> Silhouette:
        """The object's silhouette in :meth:`sensing_camera`."""
        return self.context.silhouette

    def depth_from_event(self) -> Tensor | None:
        """(4, 4) event camera -> sensing camera, ``None`` where they are the same."""
        return None

    def pose_filter(self) -> PoseUKF | PoseTwistUKF:
        """A new pose filter for this method (one track)."""
        return PoseUKF(1, self.config.pose_ukf, device=self.device)

    def bind(self, services: MotionServices) -> None:
        """Called once by the tracker, after the parts are built."""
        self.services = services

    # ------------------------------------------------------------ state
    def reset(self) -> None:
        """Start over (the tracker's reset)."""

    def lost(self) -> None:
        """The object was lost: forget the motion state."""

    def twist(self) -> np.ndarray:
        """(6,) float64 the present twist ``[v_o, ω]`` output with the pose."""
        return np.zeros(6)

    def segment_started(self, pose: np.ndarray | None) -> None:
        """A step group's segment starts at the filter's ``pose`` (4, 4) (``None``: none)."""

    def track_started(self, t_pose: int) -> None:
        """The pose of ``t_pose`` (µs) started the track (it may be from the past)."""

    # ------------------------------------------------------------ steps
    def begin_group(self, ev: Events, t0: int, t_end: int, pose: np.ndarray | None,
                    search_budget: int) -> None:
        """The step group ``[t0, t_end)`` starts; ``ev`` are its gated events (all events of
        the group for ``uses_events``), ``pose`` (4, 4) the filter's at ``t0`` (``None``:
        none), ``search_budget`` the candidate searches allowed over the group (0: no cap)."""

    def step(self, k: int, dt: float, pose: np.ndarray | None,
             poly: SilhouettePolygon | None, usable: bool) -> Tensor | None:
        """The twist (1, 6) of step ``k`` of the group (``dt`` s), for the pose filter's
        predict; ``None`` where the pose filter keeps its own motion model. ``pose``, ``poly``:
        the segment's; ``usable``: the object was not lost inside the group."""
        return None

    def keep_unposed(self, k: int, t_end: int) -> None:
        """Step ``k`` (ending at ``t_end``) ran without a pose."""

    @property
    def has_step_runs(self) -> bool:
        """Whether :meth:`run_twists` may measure several steps at once (this group)."""
        return False

    def run_twists(self, k: int, end: int, pose: np.ndarray, poly: SilhouettePolygon
                   ) -> StepRun | None:
        """The twists of steps ``k..end-1`` in one compiled call, ``None`` where that does not
        apply (never again for this tracker)."""
        return None

    # ------------------------------------------------------------ frames
    def on_rgb(self, t_us: int, read: Callable[[], np.ndarray]) -> np.ndarray | None:
        """An RGB frame at ``t_us`` (``read()`` returns it, (H, W, 3) uint8); returns the image
        where it was read (so the pose source need not read it again)."""
        return None
