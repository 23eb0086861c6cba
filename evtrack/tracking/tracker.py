"""``Tracker``: 6-DoF pose tracking from events and RGB-D frames (the method paper, Sec. III).

Data flow of the ``full`` method (docs/architecture.md), once per velocity step (1 ms by default)::

    events of the step ──► kept if within mask_margin_px of the predicted silhouette
        ──► TripletFlow (one flow window per step) ──► RoI flows (px/s)
        ──► depth at the RoIs (sensor depth frame or mesh rendered at the predicted pose)
        ──► VelocityKF (decaying-velocity predict + flow update) ──► twist [v_o, ω]
        ──► PoseUKF.predict(twist, step)  (+ the velocity bias it learns from the poses)
    RGB frames at pose_rate_hz ──► pose source ──► pose available at t + pose_latency
        ──► PoseUKF.update at the frame's time t (the filter rolls back and replays)

In :meth:`Tracker.track` the pose source runs in a worker thread meanwhile (``pose_async``):
its result is only taken when it becomes available, so the trajectory is the same.

The methods (``TrackerConfig.method``) share this code:

* ``full``: as above (the paper), with one addition by default: the pose filter learns a bias
  of the twist's velocity that grows with the object's speed from the pose innovations
  (``pose_ukf.velocity_bias``; the twists the tracker outputs are the velocity filter's,
  without it).
* ``velocity``: the same velocity pipeline; poses are used only to initialise (and to
  re-initialise after the object was lost).
* ``pose``: no velocity; the pose UKF (``pose_only_ukf``, random-walk process noise) with poses.
* ``frame-flow``: ROFT-like: dense optical flow between consecutive RGB frames
  (:mod:`evtrack.tracking.baselines.frame_flow`) -> a twist per frame pair (``frame_flow_kf``) ->
  twist
  measurement of a constant-velocity pose UKF (:class:`~evtrack.filters.PoseTwistUKF`), which is
  predicted every step and fused with the poses.
* ``ge``: the 1-DoF generative event model (:mod:`evtrack.tracking.baselines.ge_model`) in place of
the flow.

Time: one clock in µs, advanced by the events (a step ``[t_k, t_k + step)`` closes when an event
at or after its end arrives) and by :meth:`Tracker.advance` / :meth:`Tracker.push_frame`
(``push_frame(t)`` first closes every step ending at or before ``t``). Inputs must be pushed in
time order, as one merged stream: events, then the frame at ``t`` once the events before ``t``
were pushed. The tracker outputs a pose and a twist at the end of every step.

Lost object: the object counts as lost when its predicted silhouette stays outside the image
for ``lost_after_ms``, or when ``lost_after_misses`` pose-source calls in a row found nothing
(a detector finds nothing when the object has left the image, while the prediction, with no
events to follow, may stop short inside it; a miss counts when its result would have been
available, ``pose_latency_ms`` after the frame). The pose filter then forgets its state and the
next pose re-initialises it (meanwhile the last pose is held and flagged). The pose filter also
re-initialises itself after ``reinit_after`` gated poses in a row
(:class:`~evtrack.filters.PoseUKF`), and on the second of two gated poses in a row that agree
with each other (``reinit_on_agreement``: the filter has drifted off, the poses have not).
Before any of that, a pose whose frame's sensor depth contradicts it (less than
``pose_depth_min_share`` of the valid depths inside its silhouette lie in its depth range) is
dropped and counted (``poses_implausible``): a network's gross errors, which can agree with
each other, then never re-initialise the filter. Before the check, a pose is moved along its
viewing ray onto the frame's sensor depth (``pose_depth_align``,
:mod:`evtrack.tracking.pose_alignment`):
an RGB network errs mostly in range, which the depth frame measures; counted in
``poses_depth_aligned``, or ``pose_alignments_skipped`` by reason. Both read the sensor depth
frame nearest the pose's own time (within ``max_depth_age_ms``): the maps of the last
``history_ms`` are kept, so a pose that arrives late, from the pose source or handed in by
the caller, is judged against the depth of its time, not the latest frame's. A dropped
pose gives way to the first of its ``alternatives`` (the detector's other poses of that
image, most confident first) that the depth confirms (``pose_alternatives``; counted in
``poses_from_alternatives``).

Sampled search (``search_per_roi_window``): of a RoI window with more events than that, the
flow searches only a hash sample of about that many for candidates
(:func:`evtrack.flow.sampling.sampled_search`). Every event still enters the search's history,
so a searched event forms the triplets it would form in the whole stream, and the sample is
drawn by the hash that also picks the registration's data term (at most
``flow.max_events_per_roi`` events): a window whose sample still holds that many
candidate-bearing events registers the same flow as unsampled. The candidate search is most of
the flow's cost and grows with the events, while the data term does not. On the densely
textured cracker box `faster` (8.6 M events/s, the default 12 px RoIs, oracle poses) the default
64 left 41 % of the flow's events unsearched and cut the flow's time from 4.6 to 2.9 s of the
2 s sequence, at 3.90 cm / 4.98 deg against 3.88 / 4.86 (32: 66 %, 2.2 s, 4.30 / 5.04). On the
four YCB objects' benchmark set (4 kHz, oracle poses) the full method's RMSE moved by at most
0.11 deg (64); 32 made the ablation rows worse (``faster`` without the normal-flow constraint
6.28 -> 10.12 cm), 64 did not (6.45 cm).

Search budget (``max_searched_per_step``): of the events so chosen, at most that many per
velocity step (over a step group) are searched, by whole RoIs visited in a fixed hash order and
taken while they fit (``budget`` of :func:`~evtrack.flow.sampling.sampled_search`). Unlike
thinning (below), the left-out RoIs' events still enter the history: a taken RoI's flow is the
one it would have without the budget however the taken RoIs change from group to group, and
only the left-out RoIs give no flow. It bounds the search and the registration per step
whatever the event rate. On the cracker box `faster` (~5k sampled events per ms) the default
2500 took the flow from ~2.9 s to ~1.8 s of the 2 s sequence, at 3.90 cm / 4.74 deg against
3.90 / 4.98; the other YCB benchmark sequences do not reach it after their first pose.

Event bursts: a step whose events outside the object's predicted silhouette (plus
``mask_margin_px``) exceed ``burst_rate_hz`` per pixel over the image outside it is an event
burst (flicker, a sensor glitch): none of its events is used, the velocity filter only
predicts, and the step is counted in :attr:`TrackerStats.burst_steps`; for
``flow.refractory_us`` after it, the flow's burst filter takes the first event of each pixel
as the continuation of a burst (its previous events were taken out). The test needs a
predicted silhouette and at least ``_BURST_MIN_OUTSIDE`` of the image outside it, and assumes
a static camera (as the method does): a moving camera's textured background can exceed the
rate by itself, and then ``burst_rate_hz: 0`` turns the test off. Independently, at most
``max_events_per_step`` events per step (on average over a step group) enter the flow (or the
GE model): above it the group's events are thinned by cells of 2 x 2 RoIs (squares of
``2 * flow.roi_size`` pixels), deterministically and independently of how the events were
chunked. The cells are taken in one fixed pseudo-random order (a hash of the cell's index):
the first ``int(n_cells * 0.75**level)``, all their events kept, the other events counted.
The level rises as far as the budget needs and falls only when the lower level fits in 80 %
of the budget, so the kept cells change seldom. A kept cell keeps whole edges' event trails,
so its triplets and RoI flows are those of the unthinned stream, and its pixels' histories
stay whole from one group to the next. Thinning single events instead leaves every trail with
gaps, and the triplet search matches the survivors to unrelated older events: on the cracker
box (`faster`, 8.6 M events/s) a budget of 4000 events per step gave 34.5 cm / 58° by single
events, 9.2 cm / 13.8° by cells, against 4.35 cm / 6.5° unthinned.

Depth fallback: a RoI without a valid depth (no depth frame yet, a frame older than
``max_depth_age_ms``, a pushed frame without depth and no earlier one, or only missing or
out-of-range pixels in its patch) takes the predicted depth of the object's origin; each such RoI
is counted in :attr:`TrackerStats.depth_fallbacks`.

Depth range (``depth_range``, off by default; not in the paper): every sensor depth frame also
measures the object's range along its viewing ray against the mesh's surface at the filter's
pose of the frame's time (:mod:`evtrack.tracking.depth_range`; no renderer), fused at that time as a
1-D measurement (:meth:`~evtrack.filters.PoseUKF.update_range`); frames without one are
counted by reason in :attr:`TrackerStats.depth_ranges_skipped`.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import time
import warnings
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from itertools import groupby
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.config_values import checked_device
from evtrack.errors import ConfigError, EventsError
from evtrack.eval.metrics import position_errors, rotation_errors
from evtrack.events import Events, concatenate
from evtrack.filters import PoseTwistUKF, PoseUKF, VelocityKF
from evtrack.filters.lie import pivot_map
from evtrack.filters.scalar_lie import normalized, rotation_matrix, se3_exp
from evtrack.flow import FlowResult, TripletFlow, sampled_search
from evtrack.geometry import matrix_to_tq

# evtrack.models is imported here, not where depth_icp is set up: it imports torch's
# flop counter, which imports Triton where installed (CUDA builds of torch), and Triton's LLVM
# crashes the process when Mesa's (the headless OpenGL of model depth, and of depth_range
# before it used surface points) is already loaded.
from evtrack.models.depth_refine import DepthRefineConfig, DepthRefiner
from evtrack.models.estimator import check_rgb
from evtrack.runtime.blas_threads import BlasThreads
from evtrack.runtime.jit import warm_up
from evtrack.tracking.baselines.frame_flow import DenseFlow, grid_in_polygon, twist_adjoint
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.depth_range import DepthRange
from evtrack.tracking.depth_sources import (
    DepthSource,
    ModelDepth,
    SensorDepth,
    silhouette_depth_share,
)
from evtrack.tracking.pose_alignment import PoseRayAligner
from evtrack.tracking.pose_flips import HalfTurnResolver
from evtrack.tracking.pose_sources import PoseMeasurement, PoseSource, checked_pose
from evtrack.tracking.pose_timeline import PoseTimeline, pose_measurement_value
from evtrack.tracking.silhouette import Silhouette, SilhouettePolygon
from evtrack.tracking.trajectory import STATUS_LOST, STATUS_TRACKING, STATUS_WAITING, Trajectory
from evtrack.utils import threads_per_job

__all__ = ["Tracker", "TrackerStats"]

_FRAME_JITTER_US = 1000
"""A frame up to this much before a pose-source slot still takes that slot (frame timestamps
are rounded to µs, so 60 FPS frames fall a few µs either side of the 5 Hz grid)."""

_LOAD_SMOOTHING = 0.1
"""``realtime_load``: weight of the newest step group in the smoothed load (~10 groups) ..."""
_LOAD_CLIP = 2.0
"""... whose single groups count at most this many times the target (a one-off spike, such as
the first pose's catch-up, is not a trend)."""
_BACKLOG_GROUPS = 5
"""``realtime_load``: the backlog (processing time beyond the target) that starts cutting the
budgets, in step groups' stream time (200 ms at the default 40 x 1 ms)."""
_RAISE_SHARE = 0.8
"""``realtime_load``: below this share of the target the smoothed load raises the budgets
while a backlog still drains (at the floors a small machine's load can sit there: without
it the budgets stayed at their floors until the backlog had drained)."""
_BUDGET_CUT = 0.9
_BUDGET_CUT_MAX = 0.7
_BUDGET_RAISE = 1.05
"""Factors of ``realtime_load``'s budgets per step group: a cut (while the backlog is over
``_BACKLOG_GROUPS``) by ``target / smoothed load`` within ``[_BUDGET_CUT_MAX, _BUDGET_CUT]``
(0.7 at twice the target, the smoothed load's clip), and a raise."""

_POSE_DEPTH_MIN_PIXELS = 16
"""Fewest valid depth pixels in a pose's silhouette to judge it (``pose_depth_min_share``)."""

_DEPTH_TOLERANCE_M = 0.05
"""Depths within this distance outside the object's predicted depth range still count as the
object's (noise, pose error)."""

_EVENTS_CHUNK_US = 50_000
"""Offline tracking reads the events in windows of this length."""

_BURST_MIN_OUTSIDE = 0.1
"""The burst test needs at least this share of the image outside the object's silhouette."""

_THIN_CELL_ROIS = 2
"""Event thinning keeps or drops cells of this many RoIs square: a kept RoI then has kept
neighbours on most sides, whose events its border events' triplets need (with cells of one
RoI the kept RoIs' flows were twice as far off on a translating texture)."""

_THIN_RATIO = 0.75
"""Each event-thinning level keeps this share of the previous level's RoI cells."""

_THIN_HEADROOM = 0.8
"""Event thinning goes back a level (more cells) only when that level's events fit in this
share of the budget (hysteresis: the kept cells change seldom)."""

_HASH_MULTIPLIER = np.uint64(0x9E3779B97F4A7C15)
"""Fibonacci hashing of RoI cell indices (thinning keeps the cells of smallest hash first)."""

#: µs after a late first pose whose kept RoI flows must lie in its silhouette (see
#: Tracker._pose_explains_events)
_REMEASURE_CHECK_US = 50_000
#: with model depth the unposed steps only predict: the timeline holds the late pose still over
#: them, so only the earliest RoI flows after it are checked (whole steps in time order, until
#: at least this many), which a moving object's events have not yet left
_REMEASURE_CHECK_MODEL_ROIS = 20
#: fewer RoI flows than this in that span: no check
_REMEASURE_CHECK_MIN_ROIS = 10
#: only RoI flows of at least this many supporting events count in the check: the weakly
#: supported ones (the tracker reports windows from ``flow.min_support`` 2) include a few
#: from sensor noise off the object, 8 of 297 on the tests' small box against none of the
#: well-supported 90, which a right pose cannot explain
_REMEASURE_CHECK_MIN_SUPPORT = 5
#: The fewest velocity steps between two events of the stream (a frame, a measurement due, a
#: depth map expiring) that go through the filters' compiled runs (Tracker._step_run)
_MIN_RUN_STEPS = 2
#: The filters take the pose, its silhouette and the velocity filter's pivot afresh every this
#: many velocity steps of a step group (its segments), whatever ``flow_batch_steps`` is: a group
#: of 40 steps makes one flow call but four segments. With the group's first pose for all of
#: its 40 steps, the coded box of ``evtrack demo`` (320x240, seeds 0-5) erred 6 % more in
#: position than with groups of 10 (2026-12-02).
_SEGMENT_STEPS = 10

FrameInput = np.ndarray | Callable[[], np.ndarray] | None


def _check_rgb(t_us: int, rgb: Any, camera: PinholeCamera) -> np.ndarray:
    """``rgb`` if it is a uint8 (H, W, 3) image of ``camera``'s size.

    Raises:
        ValueError: naming the frame's time, what it got and what was expected.
    """
    where = f"RGB frame at t={t_us} µs"
    try:
        check_rgb(rgb)  # the pose estimators' own check of the image's format
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    if rgb.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"{where} is {rgb.shape[1]}x{rgb.shape[0]}, the RGB-D camera is "
                         f"{camera.width}x{camera.height}")
    return rgb


def _checked_rgb_reader(t_us: int, read: Callable[[], Any], camera: PinholeCamera
                        ) -> Callable[[], np.ndarray]:
    """``read`` (a frame given as a callable), its result checked by :func:`_check_rgb`."""
    return lambda: _check_rgb(t_us, read(), camera)


@dataclass
class TrackerStats:
    """Counters of one run (since the last :meth:`Tracker.reset`).

    Attributes:
        steps: velocity steps processed.
        events: events pushed.
        events_on_object: events inside the predicted silhouette.
        events_in_bursts: of those, events of burst steps (not used); burst_steps: steps
            found to be event bursts (see the module docstring).
        events_thinned: events of the cells beyond a group's ``max_events_per_step`` budget
            (not used; see the module docstring).
        events_unsearched: events given to the flow but, beyond a RoI window's
            ``search_per_roi_window``, not searched for candidates (they still serve the
            searched events' triplets; see the module docstring).
        roi_flows: RoI flows given to the velocity filter.
        velocity_updates: steps with at least one RoI flow (or GE row).
        depth_fallbacks: RoIs that took the fallback depth (see the module docstring).
        frames: frames pushed; frames_without_depth: of those, without a depth frame.
        pose_calls: pose-source calls; poses: measurements returned; poses_late: dropped
            because older than ``history_ms``; pose_misses: calls that returned nothing or a
            pose below ``pose_min_confidence``.
        poses_rejected: poses rejected by the gate; reinitialisations: filter re-inits after
            rejections; lost: times the object was declared lost.
        poses_implausible: poses dropped before the filter because the sensor depth of their
            frame contradicts them (``TrackerConfig.pose_depth_min_share``).
        poses_from_alternatives: poses that failed that check and were replaced by one of
            their :attr:`~evtrack.tracking.pose_sources.PoseMeasurement.alternatives` that passed it
            (``TrackerConfig.pose_alternatives``; not counted as implausible).
        poses_half_turned: poses replaced by their half turn about one of
            ``TrackerConfig.pose_half_turn_axes``, which lay nearer the filter's pose;
            half_turn_reinits: poses that re-initialised the filter instead, the
            ``pose_half_turn_reinit_after``-th in a row to need the turn.
        poses_depth_aligned: poses moved along their viewing ray onto the sensor depth
            (``TrackerConfig.pose_depth_align``); pose_alignments_skipped: poses that were not,
            by reason (:class:`~evtrack.tracking.pose_alignment.RayAlignment`).
        search_budget_min: with ``TrackerConfig.realtime_load``, the lowest search budget per
            step it set (0: it never lowered it); event_budget_min: the lowest event budget
            per step it set (0: it never shed events); groups_over_load: step groups whose
            processing took longer than ``realtime_load`` of their stream time.
        twist_measurements: frame-flow twist measurements fused; twists_replayed: of those,
            measured on kept frame pairs when a late pose started the track.
        steps_remeasured: velocity steps measured again, with RoI flows, once a late pose
            started the track (``remeasure_on_pose``); remeasures_skipped: late first poses
            whose steps were not measured again, the pose not explaining the events
            (``remeasure_min_inside``).
        depth_ranges: range measurements from depth frames given to the pose filter
            (``depth_range``); depth_ranges_skipped: depth frames without one, by reason
            (:class:`~evtrack.tracking.depth_range.RangeResult`).
        depth_alignments: poses aligned with depth frames given to the pose filter
            (``depth_icp``); depth_alignments_skipped: aligned frames without one, by reason
            (``"few depth pixels"``, ``"few fit"``: too few depth pixels fit the mesh,
            ``"correction too large"``).
        time_s: processing time per stage (flow, velocity, pose, frames, other).
    """

    steps: int = 0
    events: int = 0
    events_on_object: int = 0
    events_in_bursts: int = 0
    burst_steps: int = 0
    events_thinned: int = 0
    events_unsearched: int = 0
    roi_flows: int = 0
    velocity_updates: int = 0
    depth_fallbacks: int = 0
    frames: int = 0
    frames_without_depth: int = 0
    pose_calls: int = 0
    poses: int = 0
    poses_late: int = 0
    pose_misses: int = 0
    poses_rejected: int = 0
    poses_implausible: int = 0
    poses_from_alternatives: int = 0
    poses_half_turned: int = 0
    half_turn_reinits: int = 0
    poses_depth_aligned: int = 0
    pose_alignments_skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    search_budget_min: int = 0
    event_budget_min: int = 0
    groups_over_load: int = 0
    reinitialisations: int = 0
    lost: int = 0
    twist_measurements: int = 0
    twists_replayed: int = 0
    steps_remeasured: int = 0
    remeasures_skipped: int = 0
    depth_ranges: int = 0
    depth_ranges_skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    depth_alignments: int = 0
    depth_alignments_skipped: dict[str, int] = dataclasses.field(default_factory=dict)
    time_s: dict[str, float] = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class _Miss:
    """A pose-source call on the frame at ``t_us`` that found nothing."""

    t_us: int


@dataclass
class _PoseCall:
    """A pose-source call on the frame at ``t_us`` running in the tracker's worker thread;
    its result is taken when it becomes available to the filter (see
    ``TrackerConfig.pose_async``)."""

    t_us: int
    result: Future


@dataclass
class _PreparedDepth:
    """A sensor depth frame as read (for a pose source that uses depth) and its event-camera
    map, made by :meth:`SensorDepth.prepare` in :meth:`Tracker.track`'s reader thread."""

    raw: np.ndarray
    event_map: np.ndarray


@dataclasses.dataclass
class _DepthFrame:
    """A sensor depth frame (event camera, metres) waiting for the range measurement."""

    t_us: int
    depth: np.ndarray


@dataclass
class _UnposedStep:
    """A velocity step measured without a pose (all events, no silhouette): its RoI flows
    and the sensor depth frame of that time, kept to be measured again once a late pose
    starts the track (``TrackerConfig.remeasure_on_pose``)."""

    uv: np.ndarray  # (N, 2) float64 px
    flow: Tensor  # (N, 2) px/s
    normal: Tensor  # (N,) bool
    depth: tuple[np.ndarray | None, int | None]  # (map, t_us) of the sensor depth
    support: np.ndarray  # (N,) events with candidates in each RoI window


class _Timer:
    def __init__(self, totals: dict[str, float], name: str) -> None:
        self.totals, self.name = totals, name

    def __enter__(self) -> None:
        self.t0 = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        self.totals[self.name] = self.totals.get(self.name, 0.0) + time.perf_counter() - self.t0


def _load_mesh(mesh: Any):
    """ObjectMesh, a mesh file (object frame kept: no recentring) or (V, 3) vertices."""
    from evtrack.sim.objects import ObjectMesh, load_mesh

    if isinstance(mesh, ObjectMesh):
        return mesh, np.asarray(mesh.vertices, np.float64)
    if isinstance(mesh, str | Path):
        m = load_mesh(mesh, recenter=False)
        return m, np.asarray(m.vertices, np.float64)
    vertices = np.asarray(mesh, np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ConfigError(f"mesh must be an ObjectMesh, a mesh file or (V, 3) vertices, got "
                          f"an array of shape {vertices.shape}")
    return None, vertices


def _lowest(seen: int, budget: int, ceiling: int) -> int:
    """``realtime_load``'s record of the lowest budget set: ``seen`` (0: none yet) or
    ``budget`` where that is lower and not the configured ``ceiling``."""
    return budget if budget != ceiling and (not seen or budget < seen) else seen


def moved_pose(T: np.ndarray, twist: np.ndarray, dt: float) -> np.ndarray:
    """:func:`evtrack.geometry.integrate_twist` for one (4, 4) float64 pose and (6,) twist
    ``[v_o, ω]`` (camera frame) over ``dt`` seconds, on Python floats
    (:func:`evtrack.filters.scalar_lie.se3_exp`): microseconds instead of a millisecond of
    tensor dispatch, for the tracker's per-group and per-query poses."""
    xi = [float(v) * dt for v in twist]
    q, p = se3_exp((xi[0], xi[1], xi[2]), (xi[3], xi[4], xi[5]))
    step = np.eye(4)
    step[:3, :3] = rotation_matrix(q)
    step[:3, 3] = p
    return step @ np.asarray(T, np.float64)


class _Prefetched:
    """``read(i)`` for frames read in increasing order: each call also starts reading the
    next ``ahead`` frames in a worker thread (OpenCV's decoders release the GIL), so that
    later calls usually find them ready. A read's exception is raised by the call that asks
    for that frame.

    Reading one frame ahead left the tracker waiting ~0.25 s per 2 s sequence for its depth
    frames on 2 busy cores (the worker starts a frame only when the one before is taken);
    three ahead, ~0.02 s (the mustard bottle `faster`, 2 cores of an AMD EPYC with up to 50 %
    steal time, 2026-12-02).

    Args:
        read: ``read(i) -> frame``, safe to call from another thread.
        count: frames there are (``0 .. count - 1``).
        ahead: frames read ahead (>= 1).
    """

    def __init__(self, read, count: int, ahead: int = 3) -> None:
        self._read = read
        self._count = count
        self._lookahead = max(1, int(ahead))
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="evtrack-frames")
        self._ahead: dict[int, Future] = {}
        self._closed = False

    def __call__(self, index: int):
        pending = self._ahead.pop(index, None)
        for other in [k for k in self._ahead if k < index]:  # skipped: not wanted any more
            self._ahead.pop(other).cancel()
        frame = pending.result() if pending is not None else self._read(index)
        if not self._closed:
            for later in range(index + 1, min(self._count, index + 1 + self._lookahead)):
                if later not in self._ahead:
                    self._ahead[later] = self._pool.submit(self._read, later)
        return frame

    def close(self) -> None:
        """Stop the worker (a read in flight finishes; its frame is dropped). Later calls
        read in the caller's thread."""
        self._closed = True
        for pending in self._ahead.values():
            pending.cancel()
        self._ahead.clear()
        self._pool.shutdown(wait=True)


class _StepFlows:
    """The RoI flows of one step group, split by velocity step.

    The rows are put in time order once (the flow reports its windows in time order; the sort
    is stable and costs nothing then), so each step's rows are one contiguous slice: views,
    not the per-step masks over every field of the result.

    Args:
        res: the group's flow result.
        t0: start of the group (µs). step: the velocity step (µs). n_steps: steps in the group.
        dtype, device: of the velocity filter's inputs.
    """

    def __init__(self, res: FlowResult, t0: int, step: int, n_steps: int, dtype: torch.dtype,
                 device: torch.device) -> None:
        t = res.t.cpu().numpy()
        order = np.argsort(t, kind="stable")
        self.uv = res.xy.detach().cpu().numpy()[order].astype(np.float64)
        order_t = torch.from_numpy(order).to(res.flow.device)
        self.flow = res.flow[order_t].to(dtype=dtype, device=device)
        self.normal = res.normal[order_t].to(device)
        self.support = res.support.detach().cpu().numpy()[order]
        edges = t0 + step * np.arange(n_steps + 1, dtype=np.int64)
        self.bounds = np.searchsorted(t[order], edges, side="left")
        #: (depth map, first row, depths from that row on, the silhouette that gated them):
        #: see Tracker._run_depth
        self.depth_cache: tuple[np.ndarray | None, int, np.ndarray, Any] | None = None

    def step(self, k: int) -> tuple[np.ndarray, Tensor, Tensor]:
        """Step ``k``'s RoI centres (N, 2) float64 px, flows (N, 2) px/s and normal flags (N,)."""
        lo, hi = int(self.bounds[k]), int(self.bounds[k + 1])
        return self.uv[lo:hi], self.flow[lo:hi], self.normal[lo:hi]


def _quat_to_matrix(t, q) -> np.ndarray:
    """(3,), (4,) wxyz (arrays or sequences of numbers) -> (4, 4) float64. Python floats and
    one array: the tracker asks at every step, where NumPy's per-operation cost on scalars
    (~1 µs each) would be most of the time."""
    r0, r1, r2 = rotation_matrix(normalized(tuple(float(v) for v in q)))
    tx, ty, tz = (float(v) for v in t)
    return np.array([[*r0, tx], [*r1, ty], [*r2, tz], [0.0, 0.0, 0.0, 1.0]])


def _alignment_covariance(res: Any, std_m: float, std_rad: float) -> np.ndarray:
    """(6, 6) tangent covariance ``[δt, δθ]`` (m², rad²; the pose filter's left perturbation
    about the object's origin) of a depth alignment (:class:`~evtrack.models.RefineResult`):
    the fit's ``rmse² · information⁻¹`` for its motion ``[δv, δω]`` about ``res.centre``, carried
    to the origin ``t`` (``δv = δt + (t − c) × δθ``), plus the floors ``std_m²``, ``std_rad²``.
    The information is regularised by 1e-9 of its largest eigenvalue, so directions the depth
    did not see get a variance that large rather than an infinite one."""
    M = pivot_map(torch.from_numpy(res.pose[:3, 3] - res.centre)).numpy()
    info = M.T @ res.information @ M
    w, V = np.linalg.eigh(0.5 * (info + info.T))
    w = np.maximum(w, 1e-9 * max(float(w.max()), 1e-30))
    cov = (V / w) @ V.T * max(res.rmse_m, 1e-6) ** 2
    return cov + np.diag([std_m ** 2] * 3 + [std_rad ** 2] * 3)


class Tracker:
    """Track one known rigid object with an event camera and an RGB-D camera.

    Args:
        config: :class:`~evtrack.tracking.config.TrackerConfig` (default: its defaults).
        camera: the event camera.
        mesh: the object: an :class:`~evtrack.sim.objects.ObjectMesh`, a mesh file (read in its
            own frame, which must be the poses' object frame), or (V, 3) vertices (enough for
            everything but ``depth_source="model"``).
        pose_source: gives absolute poses from RGB frames (:mod:`evtrack.tracking.pose_sources`);
            ``None``: poses only through :meth:`push_pose` or :meth:`reset`.
        rgb_camera: the RGB-D camera (default: the event camera).
        T_event_rgb: (4, 4) maps RGB-camera points into the event camera (default identity).

    Attributes:
        clock: ``() -> seconds``, the wall clock ``TrackerConfig.realtime_load`` measures the
            processing with (default :func:`time.perf_counter`; replaceable, e.g. in tests).

    Example:
        >>> tracker = Tracker.for_sequence(seq, TrackerConfig(), pose_source)   # doctest: +SKIP
        >>> trajectory = tracker.track(seq)                                      # doctest: +SKIP
        >>> trajectory.save("track.csv")                                         # doctest: +SKIP
    """

    step_runs: bool = True
    """Run the velocity steps between two events of the stream (a frame, a measurement due)
    through the filters' compiled runs, a few calls for all of them, where they apply (one
    float64 track on CPU, sensor depth); off: step by step. The same trajectory either way
    (the tests compare the two)."""

    def __init__(self, config: TrackerConfig | None = None, *, camera: PinholeCamera,
                 mesh: Any, pose_source: PoseSource | None = None,
                 rgb_camera: PinholeCamera | None = None,
                 T_event_rgb: Tensor | np.ndarray | None = None) -> None:
        self.config = config if config is not None else TrackerConfig()
        cfg = self.config
        warm_up()  # numba's start-up now, not at the first events (see evtrack.runtime.jit)
        self.camera = camera
        self.rgb_camera = rgb_camera if rgb_camera is not None else camera
        self.T_event_rgb = (torch.eye(4, dtype=torch.float64) if T_event_rgb is None
                            else torch.as_tensor(T_event_rgb, dtype=torch.float64))
        if self.T_event_rgb.shape != (4, 4):
            raise ConfigError(f"T_event_rgb must be (4, 4), got {tuple(self.T_event_rgb.shape)}")
        self.pose_source = pose_source
        self.clock: Callable[[], float] = time.perf_counter
        self.mesh, vertices = _load_mesh(mesh)
        self.device = checked_device(cfg.device, "tracker config field 'device'")
        self.silhouette = Silhouette(vertices, camera)
        self.method = cfg.method
        eye = torch.eye(4, dtype=torch.float64)
        self._aligned = self.rgb_camera == camera and bool(torch.allclose(self.T_event_rgb, eye))
        # the camera whose images measure the motion: events, or RGB for frame-flow
        sensing_camera = self.rgb_camera if self.method == "frame-flow" else camera
        if self.method == "frame-flow":
            self.rgb_silhouette = Silhouette(vertices, self.rgb_camera)
            self.T_rgb_event = torch.linalg.inv(self.T_event_rgb)
            self.dense_flow = DenseFlow(cfg.frame_flow)
            self.frame_kf = VelocityKF(self.rgb_camera, 1, cfg.frame_flow_kf, device=self.device)
            self.rgb_to_event_twist = twist_adjoint(self.T_event_rgb)
        self.depth = self._make_depth_source(sensing_camera, vertices)
        self.pose_aligner: PoseRayAligner | None = None
        if cfg.pose_depth_align and self.mesh is not None and isinstance(self.depth, SensorDepth):
            self.pose_aligner = PoseRayAligner.from_mesh(
                self.mesh, self.depth.camera, max_shift_m=cfg.pose_depth_align_max_m)
        self.half_turns: HalfTurnResolver | None = None
        if cfg.pose_half_turn_axes:
            lo, hi = vertices.min(axis=0), vertices.max(axis=0)
            self.half_turns = HalfTurnResolver(cfg.pose_half_turn_axes, (lo + hi) / 2,
                                               cfg.pose_half_turn_max_view_deg)
        self.depth_range: DepthRange | None = None
        if cfg.depth_range and self.method != "velocity":
            if self.mesh is None:
                raise ConfigError("depth_range needs the object's mesh (an ObjectMesh or a "
                                  "mesh file), not bare vertices")
            self.depth_range = DepthRange(self.mesh, self.depth.camera,
                                          std_m=cfg.depth_range_std_m)
        self.depth_icp = None
        if cfg.depth_icp and self.method != "velocity":
            if self.mesh is None:
                raise ConfigError("depth_icp needs the object's mesh (an ObjectMesh or a "
                                  "mesh file), not bare vertices")
            self.depth_icp = DepthRefiner.from_mesh(self.mesh, DepthRefineConfig(
                model_points=cfg.depth_icp_points, max_scene_points=cfg.depth_icp_scene_points))
            depth_camera = self.depth.camera
            self._depth_K = depth_camera.K().numpy()
            self._depth_dist = (None if depth_camera.dist is None
                                else depth_camera.dist.numpy())
        # the depth maps are in the sensing camera (frame-flow's is the RGB camera), the
        # filter's pose in the event camera
        T = (torch.linalg.inv(self.T_event_rgb) if self.method == "frame-flow"
             else torch.eye(4, dtype=torch.float64))
        self._T_depth_event = T.numpy()
        self._T_event_depth = np.linalg.inv(self._T_depth_event)
        self.flow = TripletFlow(cfg.flow.replace(sensor_size=camera.size, device=cfg.device))
        self._blas = BlasThreads(cfg.blas_threads)
        self.vkf = VelocityKF(camera, 1, cfg.velocity_kf, device=self.device)
        if self.method == "ge":
            from evtrack.tracking.baselines.ge_model import GEVelocity

            if not self._aligned:
                raise ConfigError("method 'ge' needs the RGB frames in the event camera's image "
                                  "(same camera, identity T_event_rgb)")
            self.ge = GEVelocity(camera, cfg.ge, cfg.velocity_kf, device=self.device)
        if self.method == "pose":
            filt = PoseUKF(1, cfg.pose_only_ukf, device=self.device)
        elif self.method == "frame-flow":
            filt = PoseTwistUKF(1, cfg.pose_twist_ukf, device=self.device)
        else:
            filt = PoseUKF(1, cfg.pose_ukf, device=self.device)
        self.ukf = filt
        # before the first pose the flow runs on all events, so that a late first pose is
        # carried to the present by the measured motion (with sensor depth also measured
        # then; model depth needs the pose: its steps wait for remeasure_on_pose)
        self._velocity_before_pose = (cfg.velocity_before_pose
                                      and self.method in ("full", "velocity"))
        # ... and the steps measured so are measured again once that pose is there
        self._remeasure_on_pose = self._velocity_before_pose and cfg.remeasure_on_pose
        self.timeline = PoseTimeline(filt, int(round(cfg.history_ms * 1e3)))
        self._zero_twist = torch.zeros(1, 6, dtype=torch.float64, device=self.device)
        self._pose_pool: ThreadPoolExecutor | None = None  # see TrackerConfig.pose_async
        self._async_poses = False  # inside track() with pose_async
        self.reset()

    def _make_depth_source(self, cam: PinholeCamera, vertices: np.ndarray) -> DepthSource:
        cfg = self.config
        if cfg.depth_source == "model":
            if self.mesh is None:
                raise ConfigError("depth_source 'model' needs the object's mesh (an ObjectMesh "
                                  "or a mesh file), not bare vertices")
            return ModelDepth(self.mesh, cam, cfg.model_depth_scale, cfg.model_depth_interval_us,
                              cfg.depth_patch_px, cfg.depth_stride_px)
        if cam is self.rgb_camera and self.method == "frame-flow":
            return SensorDepth(cam, cam, None, cfg.depth_patch_px, cfg.depth_stride_px)
        return SensorDepth(cam, self.rgb_camera, self.T_event_rgb, cfg.depth_patch_px,
                           cfg.depth_stride_px)

    @classmethod
    def for_sequence(cls, sequence, config: TrackerConfig | None = None,
                     pose_source: PoseSource | None = None) -> Tracker:
        """A tracker with the cameras, extrinsics and mesh of a :class:`~evtrack.Sequence`.

        Warns (``UserWarning``) when the pose source's network was trained for another object
        than the sequence's (both names known): its poses would be another object's.
        """
        mesh = sequence.mesh_file
        if mesh is None:
            raise ConfigError(f"{sequence.root or sequence.meta.name}: the sequence names no "
                              "object mesh (meta.yaml object.mesh)")
        trained_for = getattr(getattr(pose_source, "estimator", None), "object_name", "")
        tracked = sequence.meta.object_name
        if trained_for and tracked and trained_for != tracked:
            warnings.warn(f"the pose source's network was trained for {trained_for!r}, but the "
                          f"sequence's object is {tracked!r}: its poses are not of this object "
                          "(use that object's weights, e.g. evtrack.models.list_weights())",
                          UserWarning, stacklevel=2)
        return cls(config, camera=sequence.meta.event_camera, mesh=mesh, pose_source=pose_source,
                   rgb_camera=sequence.meta.rgb_camera, T_event_rgb=sequence.meta.T_event_rgb)

    # ------------------------------------------------------------------ state
    def reset(self, pose: Tensor | np.ndarray | None = None, t_us: int | None = None) -> None:
        """Start over. With ``pose`` (4, 4) the track starts at ``t_us`` (required then) from
        that pose; without, it waits for the first pose from the pose source.

        Raises:
            ValueError: a pose without ``t_us``, or not a rigid (4, 4) transform (checked
                before anything is reset).
        """
        if pose is not None and t_us is None:
            raise ValueError("reset: a starting pose needs its time t_us")
        if pose is not None:  # checked before anything is reset
            pose = checked_pose(pose, f"reset: starting pose at t={int(t_us)} µs")
        self.flow.reset()
        self.vkf.reset(1)
        self.ukf.reset(1)
        if self.method == "frame-flow":
            self.dense_flow.reset()
            self._ff_backlog: deque[tuple[Any, tuple | None]] = deque()
        if self.method == "ge":
            self.ge.reset()
        if isinstance(self.depth, SensorDepth):
            self.depth.map, self.depth.t_us = None, None
        elif isinstance(self.depth, ModelDepth):
            self.depth.invalidate()
        self.stats = TrackerStats()
        self._last_alignment_us: int | None = None  # depth_icp: last aligned frame's time
        self._t: int | None = None
        self._ev_buf: list[Events] = []
        self._thin_level = 0  # event thinning keeps 0.75**level of the RoI cells (_thin)
        self._burst_ends: list[int] = []  # µs: ends of this group's bursts (_in_burst)
        self._resync: tuple[int, int] | None = None  # µs: a flow re-sync going on (_flow_update)
        self._resync_seen = np.zeros(0, bool)  # pixels with an event in that re-sync so far
        self._search_budget = self.config.max_searched_per_step  # per step (realtime_load)
        self._event_budget = self.config.max_events_per_step  # per step, 0: none (the same)
        # events per step entering the thinning, smoothed over ~10 step groups
        self._events_per_step: float | None = None
        self._backlog_s = 0.0  # processing beyond realtime_load of the stream time, s
        self._load: float | None = None  # smoothed processing / stream time (realtime_load)
        self._last_event_t: int | None = None
        self._runs_declined = False  # the filters' compiled runs do not apply (_step_run)
        self._pending: list[tuple[int, int, PoseMeasurement | _Miss | _DepthFrame | tuple]] = []
        self._pending_seq = 0
        self._next_pose_slot: int | None = None
        self._ever_lost = False
        self._out_of_view_us = 0
        self._misses = 0  # pose-source misses in a row
        self._rejected_pose: tuple[int, Tensor] | None = None  # the last pose, if gated
        self._half_turns_in_row = 0  # fused poses turned by pose_half_turn_axes in a row
        self._depth_frames: dict[int, np.ndarray] = {}  # recent sensor maps by frame time
        self._held: np.ndarray | None = None
        self._unposed: dict[int, _UnposedStep] = {}  # by step end (µs), see _remeasure
        self._out_t: list[int] = []
        self._out_tq: list[np.ndarray] = []
        self._out_twist: list[np.ndarray] = []
        self._out_status: list[int] = []
        self._frames: list[tuple[int, int, FrameInput, FrameInput]] = []
        self._frame_seq = 0
        self._horizon = -(1 << 62)
        self._clock_moved_by = "reset"  # the call that last moved the clock (for errors)
        if t_us is not None:
            self._start_clock(int(t_us))
        if pose is not None:
            t, q = pose_measurement_value(pose, torch.float64, self.device)
            self.ukf.reset(1, t=t, q=q)
            self.timeline.start(self._t)

    def _start_clock(self, t_us: int) -> None:
        step = self.config.velocity_step_us
        self._t = (t_us // step) * step
        self.timeline.start(self._t)

    @property
    def initialized(self) -> bool:
        """Whether the pose filter holds a pose."""
        return bool(self.ukf.initialized.item())  # one track; .item(): ~1 µs, asked per step

    @property
    def status(self) -> int:
        """:data:`~evtrack.tracking.trajectory.STATUS_WAITING`, ``STATUS_TRACKING`` or
        ``STATUS_LOST``."""
        if self.initialized:
            return STATUS_TRACKING
        return STATUS_LOST if self._ever_lost else STATUS_WAITING

    @property
    def now_us(self) -> int | None:
        """The clock: end of the last closed velocity step (µs), ``None`` before any input."""
        return self._t

    def _current_pose(self) -> np.ndarray:
        return _quat_to_matrix(self.ukf.t.tolist()[0], self.ukf.q.tolist()[0])

    def _current_twist(self) -> np.ndarray:
        if self.method == "pose":
            return np.zeros(6)
        source = (self.ukf if self.method == "frame-flow"
                  else self.ge if self.method == "ge" else self.vkf)
        return np.array(source.twist.tolist()[0], np.float64)

    # ------------------------------------------------------------------ inputs
    def push_events(self, events: Events) -> None:
        """Add the next events of the stream (time-sorted, not before earlier ones).

        Raises:
            EventsError: unsorted events, events before the previous ones or before the
                current step, events outside the sensor.
        """
        if not isinstance(events, Events):
            raise EventsError(f"push_events expects an Events container, got "
                              f"{type(events).__name__}")
        if events.sensor_size is not None and tuple(events.sensor_size) != self.camera.size:
            raise EventsError(f"events of sensor size {tuple(events.sensor_size)} given to a "
                              f"tracker for a {self.camera.size} camera")
        if not len(events):
            return
        report = events.validate(self.camera.size)
        if not report.ok:
            raise EventsError(f"push_events: {report}")
        t_first, t_last = events.t_start, events.t_end
        if self._last_event_t is not None and t_first < self._last_event_t:
            raise EventsError(f"push_events: events start at t={t_first} µs, before the last "
                              f"event pushed (t={self._last_event_t} µs)")
        if self._t is not None and t_first < self._t:
            raise EventsError(f"push_events: events start at t={t_first} µs, before the "
                              f"tracker's clock ({self._t} µs, moved there by "
                              f"{self._clock_moved_by}); push events and frames in time order, "
                              "all on the stream's clock")
        if self._t is None:
            self._start_clock(t_first)
        self._last_event_t = t_last
        self._clock_moved_by = f"push_events (events up to t={t_last} µs)"
        self.stats.events += len(events)
        self._ev_buf.append(events.to("cpu"))
        self._advance_to(t_last)

    def advance(self, t_us: int) -> None:
        """Declare that every event before ``t_us`` was pushed: close the step groups (of
        ``flow_batch_steps`` steps) ending by then, and the frames before them."""
        t_us = int(t_us)
        if t_us > self._horizon:
            self._clock_moved_by = f"advance(t_us={t_us})"
        self._advance_to(t_us)

    def _advance_to(self, t_us: int) -> None:
        """:meth:`advance` for the input calls (which name themselves as the clock's mover)."""
        t_us = int(t_us)
        if self._t is None:
            self._start_clock(t_us)
        self._horizon = max(self._horizon, t_us)
        with self._blas:
            self._advance(t_us, whole_groups=True)

    def flush(self) -> None:
        """Close every step ending by the latest time known (the last event pushed or the last
        :meth:`advance`), also inside an unfinished step group, and process the frames queued up
        to then. Call it at the end of a stream."""
        if self._t is None:
            return
        with self._blas:
            self._advance(self._horizon, whole_groups=False)
            self._frames_due(self._horizon + 1)
        self._settle_pose_calls()

    def _settle_pose_calls(self) -> None:
        """Wait for the worker's pose-source calls that are not due yet and leave their
        results pending as the synchronous path would have (poses and misses counted, the
        pose or the miss scheduled for its time): the end of a stream then leaves the same
        state and statistics either way."""
        calls = [entry for entry in self._pending if isinstance(entry[2], _PoseCall)]
        if not calls:
            return
        self._pending = [entry for entry in self._pending if not isinstance(entry[2], _PoseCall)]
        for available, seq, call in calls:
            with _Timer(self.stats.time_s, "pose_wait"):
                m = call.result.result()
            if m is not None and m.confidence >= self.config.pose_min_confidence:
                self.stats.poses += 1
                self._pending.append((max(m.t_us, available), seq, m))
            else:
                self.stats.pose_misses += 1
                self._pending.append((available, seq, _Miss(call.t_us)))
        heapq.heapify(self._pending)

    def push_frame(self, t_us: int, rgb: FrameInput = None, depth: FrameInput = None) -> None:
        """Add the RGB-D frame taken at ``t_us`` (after the events before ``t_us``).

        The frame is processed once the clock reaches it (after the steps ending by ``t_us``);
        a frame older than the clock is processed at once. A depth frame older than the depth
        map in use does not replace it (the RoIs keep the newer one); it still serves the
        pose checks of its own time and the depth fusions (``depth_range``, ``depth_icp``).

        Args:
            t_us: frame time (µs).
            rgb: (H, W, 3) uint8 RGB of the RGB-D camera, or a zero-argument callable that
                returns it (called only when the frame is needed), or ``None``.
            depth: (H, W) metres (NaN or <= 0 = missing), a callable returning it, or ``None``
                (sensor depth: the previous depth frame is kept, see the module docstring).

        Raises:
            ValueError: an RGB or depth array of the wrong shape or type (nothing is queued).
                A frame given as a callable is read when it is processed, so its errors are
                raised then, from the call that processed it, naming the frame's time; the
                tracker stays usable (the steps of the step group it interrupted get no
                flow).
        """
        t_us = int(t_us)
        if depth is not None and not callable(depth) and isinstance(self.depth, SensorDepth):
            self.depth.check_frame(t_us, depth)
        self._clock_moved_by = f"push_frame(t_us={t_us})"
        if rgb is not None and not callable(rgb) and self._uses_rgb:
            _check_rgb(t_us, rgb, self.rgb_camera)
        if self._t is None:
            self._start_clock(t_us)
        self.stats.frames += 1
        if depth is None:
            self.stats.frames_without_depth += 1
        self._frame_seq += 1
        heapq.heappush(self._frames, (t_us, self._frame_seq, rgb, depth))
        with self._blas:
            if t_us < self._t:
                self._frames_due(self._t)
            self._advance_to(t_us)

    @property
    def _uses_rgb(self) -> bool:
        """Whether the RGB images are read: by the pose source or the frame-based methods."""
        return self.pose_source is not None or self.method in ("frame-flow", "ge")

    def _frames_due(self, t_before: int) -> None:
        """Process the queued frames taken before ``t_before``."""
        while self._frames and self._frames[0][0] < t_before:
            t_us, _, rgb, depth = heapq.heappop(self._frames)
            with _Timer(self.stats.time_s, "frames"):
                try:
                    self._process_frame(t_us, rgb, depth)
                except Exception as exc:
                    if hasattr(exc, "add_note"):  # Python >= 3.11
                        exc.add_note(f"(while processing the frame pushed for t={t_us} µs; "
                                     "the tracker goes on without it)")
                    raise

    @property
    def _source_uses_depth(self) -> bool:
        return bool(getattr(self.pose_source, "uses_depth", False))

    def _process_frame(self, t_us: int, rgb: FrameInput, depth: FrameInput) -> None:
        depth_map: np.ndarray | None = None
        if depth is not None and isinstance(self.depth, SensorDepth):
            depth_map = depth() if callable(depth) else depth
            if isinstance(depth_map, _PreparedDepth):  # from track(): prepared ahead
                event_map, depth_map = depth_map.event_map, depth_map.raw
            else:
                event_map = self.depth.prepare(t_us, depth_map)
            if self.depth.t_us is None or t_us >= self.depth.t_us:
                self.depth.set_prepared(t_us, event_map)  # else the newer map stays in use
            self._remember_depth(t_us, event_map)
            if self.depth_range is not None or self.depth_icp is not None:
                self._schedule(t_us, _DepthFrame(t_us, event_map))
                self._apply_due(self._t)
        if rgb is None:
            return
        get_rgb = _checked_rgb_reader(t_us, rgb, self.rgb_camera) if callable(rgb) else (
            lambda: rgb)
        image: np.ndarray | None = None
        if self.method == "frame-flow":
            image = get_rgb()
            self._frame_flow(t_us, image)
        if self.method == "ge":
            image = image if image is not None else get_rgb()
            self.ge.set_frame(t_us, image, self.pose(t_us) if self.initialized else None)
        if self._wants_pose(t_us):
            self.stats.pose_calls += 1
            available = t_us + self.config.pose_latency_us
            uses_depth = self._source_uses_depth
            if depth_map is None and depth is not None and uses_depth:
                depth_map = depth() if callable(depth) else depth
            depth_in = depth_map if uses_depth else None
            prior = self._pose_prior(t_us)
            if self._async_poses and available > self._t:
                # computed in the worker (the RGB frame read there too), taken at
                # `available`: the same result at the same moment for the filter
                self._schedule(available, _PoseCall(t_us, self._pose_worker().submit(
                    self._call_pose_source, t_us, image if image is not None else get_rgb,
                    depth_in, prior)))
                return
            m = self._call_pose_source(t_us, image if image is not None else get_rgb(),
                                       depth_in, prior)
            if m is not None and m.confidence >= self.config.pose_min_confidence:
                self.push_pose(m, available_us=available)
            else:
                self.stats.pose_misses += 1
                self._schedule(max(available, self._t), _Miss(t_us))
                self._apply_due(self._t)

    def _remember_depth(self, t_us: int, event_map: np.ndarray) -> None:
        """Keep the sensor depth map just taken (frame time ``t_us``) for the poses of its time
        (:meth:`_depth_checked`), and forget the maps older than the kept past
        (``history_ms`` before the newest): a pose that arrives late, from the pose source
        after its latency or from the caller, is checked against the frame of its own time,
        not against whatever frame came last. Costs one map per depth frame of that past
        (640x480 float32: 1.2 MB each, ~37 MB at 30 Hz and the default 1 s)."""
        if not self._checks_pose_depth():
            return
        self._depth_frames[t_us] = event_map
        oldest = max(self._depth_frames) - self.config.history_ms * 1e3
        for t_old in [t for t in self._depth_frames if t < oldest]:
            del self._depth_frames[t_old]

    def _depth_fresh(self, t_depth: int | None, t_us: int) -> bool:
        return t_depth is not None and abs(t_us - t_depth) <= self.config.max_depth_age_ms * 1e3

    def _checks_pose_depth(self) -> bool:
        """Whether poses are aligned with or checked against sensor depth frames."""
        return isinstance(self.depth, SensorDepth) and bool(
            self.config.pose_depth_min_share or self.pose_aligner is not None)

    def _pose_frame_depth(self, t_us: int) -> np.ndarray | None:
        """The kept sensor depth map nearest in time to a pose at ``t_us`` (the earlier of two
        as near), within ``max_depth_age_ms`` of it; ``None`` without one."""
        fresh = [t for t in self._depth_frames if self._depth_fresh(t, t_us)]
        if not fresh:
            return None
        return self._depth_frames[min(fresh, key=lambda t: (abs(t - t_us), t))]

    def _depth_checked(self, m: PoseMeasurement) -> PoseMeasurement | None:
        """The pose aligned along its viewing ray with its frame's sensor depth
        (``TrackerConfig.pose_depth_align``; unchanged when it cannot be), or ``None`` when that
        depth contradicts it (``TrackerConfig.pose_depth_min_share``). Sensor maps lie in the
        depth source's camera: the event camera's, the RGB camera's for frame-flow."""
        if not self._checks_pose_depth():
            return m
        depth = self._pose_frame_depth(m.t_us)
        if depth is None:
            return m
        pose = m.pose.detach().cpu().numpy()
        if self.method == "frame-flow":
            pose, silhouette = self.T_rgb_event.numpy() @ pose, self.rgb_silhouette
        else:
            silhouette = self.silhouette
        if self.pose_aligner is not None:
            res = self.pose_aligner.align(depth, pose)
            if res.ok:
                self.stats.poses_depth_aligned += 1
                pose = res.pose
                aligned = (self.T_event_rgb.numpy() @ pose if self.method == "frame-flow"
                           else pose)
                m = dataclasses.replace(m, pose=torch.as_tensor(aligned, dtype=m.pose.dtype))
            else:
                skipped = self.stats.pose_alignments_skipped
                skipped[res.reason] = skipped.get(res.reason, 0) + 1
        share_min = self.config.pose_depth_min_share
        if not share_min:
            return m
        poly = silhouette.polygon(pose)
        if poly is None:
            return m
        share, count = silhouette_depth_share(depth, poly, self.config.pose_depth_tolerance_m)
        return None if count >= _POSE_DEPTH_MIN_PIXELS and share < share_min else m

    def _pose_prior(self, t_us: int) -> np.ndarray | None:
        """(4, 4) the pose (event camera frame) handed to the pose source for the frame at
        ``t_us`` (``TrackerConfig.pose_prior``), or ``None``: no prior wanted, a source that
        takes none, or no track (before the first pose, after a loss)."""
        if not (self.config.pose_prior and self.initialized
                and getattr(self.pose_source, "accepts_prior", False)):
            return None
        return np.array(self.pose(t_us), dtype=np.float64)

    def _call_pose_source(self, t_us: int, image: np.ndarray | Callable[[], np.ndarray],
                          depth: np.ndarray | None, prior: np.ndarray | None = None
                          ) -> PoseMeasurement | None:
        """The pose source on one frame (``image`` may be a reader, called here), timed;
        ``prior`` (from :meth:`_pose_prior`) is passed only when there is one."""
        with _Timer(self.stats.time_s, "pose_source"):
            rgb = image() if callable(image) else image
            if prior is None:
                return self.pose_source(t_us, rgb, depth)
            return self.pose_source(t_us, rgb, depth, prior=prior)

    def _take_pose_call(self, call: _PoseCall, available: int, t_now: int) -> None:
        """A worker's pose-source result, due at ``available`` (<= ``t_now``): handled as the
        synchronous path's pose or miss, scheduled for ``available`` at the frame's turn,
        would be now."""
        with _Timer(self.stats.time_s, "pose_wait"):
            m = call.result.result()  # a pose source's exception is raised here
        if m is not None and m.confidence >= self.config.pose_min_confidence:
            self.stats.poses += 1
            due = max(m.t_us, available)
            if due <= t_now:
                self._fuse_pose(m)
            else:  # a measurement time after the frame's (not from the built-in sources)
                self._schedule(due, m)
        else:
            self.stats.pose_misses += 1
            self._on_miss(t_now)

    def _pose_worker(self) -> ThreadPoolExecutor:
        """The one thread that runs the pose source in :meth:`track` with ``pose_async``
        (calls in frame order)."""
        if self._pose_pool is None:
            self._pose_pool = ThreadPoolExecutor(max_workers=1,
                                                 thread_name_prefix="evtrack-pose")
        return self._pose_pool

    def push_pose(self, measurement: PoseMeasurement, available_us: int | None = None) -> None:
        """Add a pose measurement (e.g. from a pose network running in another thread).

        A pose is fused at its own time and carried to the present. One older than the
        tracker's past (before its first input, or more than ``history_ms`` before the clock)
        cannot be and is counted in ``stats.poses_late``: to start a track from a pose taken
        before the first events, give it to :meth:`reset` (``reset(pose, t_us)``), or push
        it before them.

        Args:
            measurement: pose of the object at ``measurement.t_us`` (event camera frame).
            available_us: when the filter may use it (default: now, or its own time if later).
        """
        if self._t is None:
            self._start_clock(measurement.t_us)
            self._clock_moved_by = f"push_pose(t_us={measurement.t_us})"
        avail = max(measurement.t_us, self._t if available_us is None else int(available_us))
        self.stats.poses += 1
        self._schedule(avail, measurement)
        with self._blas:
            self._apply_due(self._t)

    def _schedule(self, available_us: int,
                  item: PoseMeasurement | _Miss | _DepthFrame | tuple) -> None:
        self._pending_seq += 1
        heapq.heappush(self._pending, (available_us, self._pending_seq, item))

    def _wants_pose(self, t_us: int) -> bool:
        if self.pose_source is None:
            return False
        if self.method == "velocity" and self.initialized:
            return False
        period = self.config.pose_period_us
        if self._next_pose_slot is None:
            self._next_pose_slot = t_us
        if t_us + _FRAME_JITTER_US < self._next_pose_slot:
            return False
        while self._next_pose_slot <= t_us + _FRAME_JITTER_US:
            self._next_pose_slot += period
        return True

    # ------------------------------------------------------------------ the clock
    def _advance(self, t_us: int, whole_groups: bool) -> None:
        """Close the step groups ending at or before ``t_us`` (or every step, see :meth:`flush`)."""
        step = self.config.velocity_step_us
        group = step * self.config.flow_batch_steps
        end = (t_us // group) * group if whole_groups else (t_us // step) * step
        if end <= self._t:
            return
        ev = concatenate(self._ev_buf) if len(self._ev_buf) > 1 else (
            self._ev_buf[0] if self._ev_buf else Events.empty(self.camera.size))
        g_start = self._t
        try:
            while g_start < end:
                g_end = min((g_start // group + 1) * group, end)
                k = int(torch.searchsorted(ev.t, torch.tensor([g_end]))[0]) if len(ev) else 0
                group_ev, ev = ev[:k], ev[k:]
                self._group(g_start, g_end, group_ev)
                g_start = g_end
        finally:
            # also when a step raised (e.g. a frame read lazily that failed its checks): the
            # interrupted group's events are spent, so the stream goes on from the next group
            # (the rest of that group gets no flow) instead of failing on every later call
            self._ev_buf = [ev] if len(ev) else []

    def _group(self, t0: int, t_end: int, ev: Events) -> None:
        """:meth:`_group_steps`, timed for ``realtime_load``."""
        started = self.clock() if self.config.realtime_load else 0.0
        self._group_steps(t0, t_end, ev)
        if self.config.realtime_load:
            self._adapt_budgets(self.clock() - started, (t_end - t0) * 1e-6)

    def _adapt_budgets(self, wall_s: float, stream_s: float) -> None:
        """``realtime_load``: from a step group's processing time ``wall_s`` and its stream
        time ``stream_s``, the search and event budgets per step of the next groups.

        The processing time beyond ``realtime_load`` of the stream time accumulates as a
        backlog (a live stream's events waiting), which drains when the groups take less.
        While the backlog exceeds ``_BACKLOG_GROUPS`` groups' stream time and the load,
        smoothed over ~10 groups and the group's own, is above the target (the group's own
        keeps the smoothed one's lag from cutting on), both budgets are cut per group by
        ``target / load`` (within ``_BUDGET_CUT_MAX`` and ``_BUDGET_CUT``):

        - the search budget down to ``min_searched_per_step``;
        - the event budget (events thinned by cells, as by ``max_events_per_step``) down to
          ``min_events_per_step``, from the events per step (smoothed over ~10 groups) where
          those are fewer than the budget or there is no cap; not where they are fewer than
          ``min_events_per_step`` already.

        While the smoothed load is below the target and there is no backlog, or it is below
        ``_RAISE_SHARE`` of the target, both grow by ``_BUDGET_RAISE`` per group, towards
        ``max_searched_per_step`` and ``max_events_per_step`` (or no cap, once the budget is
        twice the events per step); otherwise they hold. The average load so stays near
        ``realtime_load`` with a bounded delay where the floors allow it; a burst the budgets
        cannot absorb (e.g. the first pose's catch-up) only drains. Cutting both together
        costs less accuracy than cutting the search alone to a low floor (cracker box
        `faster`: 2500 events and 1000 searched per step, 3.6 cm / 8.7 deg, ran about as fast
        as 2000 and 250, 9.5 cm / 16.6 deg, on 2 cores of an AMD EPYC, 2026-12-02)."""
        cfg = self.config
        target = cfg.realtime_load
        load = wall_s / stream_s
        if load > target:
            self.stats.groups_over_load += 1
        counted = min(load, _LOAD_CLIP * target)
        self._load = counted if self._load is None else (
            _LOAD_SMOOTHING * counted + (1 - _LOAD_SMOOTHING) * self._load)
        self._backlog_s = max(0.0, self._backlog_s + wall_s - target * stream_s)
        search, events = self._search_budget, self._event_budget
        if self._backlog_s > _BACKLOG_GROUPS * stream_s and self._load > target < load:
            cut = min(max(target / self._load, _BUDGET_CUT_MAX), _BUDGET_CUT)
            search = max(int(search * cut), cfg.min_searched_per_step)
            if (self._events_per_step or 0.0) > cfg.min_events_per_step > 0:  # thinning can help
                rate = math.ceil(self._events_per_step)
                base = min(events, rate) if events else rate
                events = max(int(base * cut), cfg.min_events_per_step)
        elif self._load < target and (self._backlog_s == 0.0
                                      or self._load < _RAISE_SHARE * target):
            search = min(int(search * _BUDGET_RAISE) + 1, cfg.max_searched_per_step)
            if events and events != cfg.max_events_per_step:
                events = int(events * _BUDGET_RAISE) + 1
                if cfg.max_events_per_step:
                    events = min(events, cfg.max_events_per_step)
                elif events > 2 * (self._events_per_step or 0.0):
                    events = 0  # far above the events: back to no cap
        st = self.stats
        st.search_budget_min = _lowest(st.search_budget_min, search, cfg.max_searched_per_step)
        st.event_budget_min = _lowest(st.event_budget_min, events, cfg.max_events_per_step)
        self._search_budget, self._event_budget = search, events

    def _group_steps(self, t0: int, t_end: int, ev: Events) -> None:
        """Process the steps of ``[t0, t_end)``: one flow call for all of them (the mask is the
        silhouette predicted at ``t0``), then the filters step by step."""
        cfg = self.config
        st = self.stats
        step = cfg.velocity_step_us
        self._frames_due(t0 + step)
        pose = self._current_pose() if self.initialized else None
        poly = self.silhouette.polygon(pose) if pose is not None else None
        events_based = self.method in ("full", "velocity", "ge")
        self._burst_ends = []
        if events_based:
            if poly is not None and len(ev):
                mask = self._swept_mask(poly, pose, t_end - t0)
                keep = mask.contains_pixels(ev.x.numpy(), ev.y.numpy(), cfg.mask_margin_px,
                                            self.camera.size)
                st.events_on_object += int(keep.sum())
                if cfg.burst_rate_hz > 0:
                    keep &= ~self._in_burst(ev.t.numpy(), keep, mask, t0, t_end)
                ev = ev[torch.from_numpy(keep)]
            elif not (pose is None and self._velocity_before_pose and self.method != "ge"):
                ev = ev[:0]
            rate = len(ev) / ((t_end - t0) // step)
            self._events_per_step = rate if self._events_per_step is None else (
                _LOAD_SMOOTHING * rate + (1 - _LOAD_SMOOTHING) * self._events_per_step)
            budget = self._event_budget * ((t_end - t0) // step)
            if budget and (len(ev) > budget or self._thin_level):
                ev = self._thin(ev, budget)
            elif not budget:
                self._thin_level = 0  # no cap (any more): nothing thinned
        res: _StepFlows | None = None
        if self.method in ("full", "velocity"):
            self._set_pivot(pose)  # the segment's pose: one pivot for its steps
            with _Timer(st.time_s, "flow"):
                # group ends are whole steps, and steps whole flow windows (the config
                # checks it): every window of the group is over, one registration reports all
                search = None
                budget = self._search_budget * ((t_end - t0) // step)
                if (cfg.search_per_roi_window or budget) and len(ev):
                    fc = self.flow.config
                    search = sampled_search(ev.x, ev.y, ev.t, self.flow.events_seen,
                                            roi_size=fc.roi_size, window_us=fc.window_us,
                                            sensor_width=self.camera.width,
                                            per_window=cfg.search_per_roi_window,
                                            budget=budget)
                    st.events_unsearched += int(len(search) - np.count_nonzero(search.numpy()))
                res = _StepFlows(self._flow_update(ev, t_end, search), t0, step,
                                 (t_end - t0) // step, self.vkf.twist.dtype, self.device)
        n_steps = (t_end - t0) // step
        ev_cut = torch.searchsorted(ev.t, t0 + step * torch.arange(
            1, n_steps + 1, dtype=torch.int64)).tolist() if len(ev) else None
        runs = (res is not None and self.step_runs and not self._runs_declined
                and isinstance(self.depth, SensorDepth) and self.timeline.twist_driven)
        k = 0
        while k < n_steps:
            b = t0 + (k + 1) * step
            if k:
                self._frames_due(b)
            initialized = self.initialized  # asked once a step (a tensor read): _frames_due
            # may change it; nothing below does before the step's filters
            if k and k % _SEGMENT_STEPS == 0 and initialized:
                # a new segment: the filter's pose now (also when the group started without
                # one: a pose that started the track inside the group)
                pose, poly = self._segment_pose()
            if runs and initialized and pose is not None and poly is not None:
                end = min(self._quiet_end(t0, k, n_steps),
                          (k // _SEGMENT_STEPS + 1) * _SEGMENT_STEPS)
                if end - k >= _MIN_RUN_STEPS:
                    done = self._step_run(t0, k, end, res, poly, pose)
                    if done is None:  # the filters' compiled paths do not apply
                        self._runs_declined, runs = True, False
                    elif done > k:
                        k = done
                        continue
            usable = pose is None or initialized  # lost inside the group: predict only
            dt = step * 1e-6
            twist: Tensor | None = None
            if res is not None:
                with _Timer(st.time_s, "velocity"):
                    if usable:
                        twist = self._velocity_step(dt, res, k, poly, pose)
                    else:
                        twist = self.vkf.predict(dt)
                    if pose is None and self._remeasure_on_pose:
                        self._keep_unposed(b, res, k)
            elif self.method == "ge":
                lo = ev_cut[k - 1] if (ev_cut and k) else 0
                ev_k = ev[lo:ev_cut[k]] if ev_cut else ev
                with _Timer(st.time_s, "velocity"):
                    twist = self.ge.step(
                        dt, ev_k, pose if (poly is not None and usable) else None,
                        lambda uv, poly=poly, pose=pose: self._roi_depth(uv, poly, pose,
                                                                         patch=False))
                    st.velocity_updates += int(self.ge.last_rows > 0)
            elif self.method == "pose":
                twist = self._zero_twist
            with _Timer(st.time_s, "pose"):
                self.timeline.step(b, twist if self.timeline.twist_driven else None)
                self._t = b
                self._apply_due(b)
            st.steps += 1
            self._check_view(b)
            self._record(b)
            k += 1

    def _swept_mask(self, poly: SilhouettePolygon, pose: np.ndarray,
                    span_us: int) -> SilhouettePolygon:
        """The polygon that masks a step group's events: the convex hull of the silhouette
        at the group's start (``poly`` at ``pose``) and the one predicted ``span_us`` later
        with the current twist, so that the object's events stay inside the mask while it
        moves through the group (a group of 40 ms at 1,000 px/s moves it 40 px, more than
        the mask's margin). The start's silhouette alone where the prediction is not finite
        or the object would not be in front of the camera."""
        twist = self._current_twist()
        if not (np.isfinite(twist).all() and np.any(twist)):
            return poly
        end = moved_pose(pose, twist, span_us * 1e-6)
        end_poly = self.silhouette.polygon(end) if np.isfinite(end).all() else None
        return poly if end_poly is None else self.silhouette.hull([poly, end_poly])

    def _set_pivot(self, pose: np.ndarray | None) -> None:
        """The velocity filter's pivot (object-centred process noise): the object's centre at
        ``pose``, or none without a finite pose."""
        if self.config.velocity_kf.object_centred:
            self.vkf.set_pivot(None if pose is None or not np.isfinite(pose).all()
                               else torch.from_numpy(np.ascontiguousarray(pose[:3, 3])))

    def _segment_pose(self) -> tuple[np.ndarray, SilhouettePolygon | None]:
        """The pose and silhouette of a new segment of a step group (see
        :data:`_SEGMENT_STEPS`): the pose filter's now; the velocity filter's pivot follows."""
        pose = self._current_pose()
        poly = self.silhouette.polygon(pose) if np.isfinite(pose).all() else None
        if self.method in ("full", "velocity"):
            self._set_pivot(pose)
        return pose, poly

    def _quiet_end(self, t0: int, k: int, n_steps: int) -> int:
        """The end (exclusive) of the steps from ``k`` of the group starting at ``t0`` that
        nothing falls between: no queued frame is due before one of them, no pending
        measurement is due at its end, and the sensor depth map does not expire at its start
        (the steps' depths are one lookup)."""
        step = self.config.velocity_step_us
        end = n_steps
        if self._frames:  # frames before b_j are taken at the start of step j > k
            end = min(end, max(k + 1, (self._frames[0][0] - t0) // step))
        if self._pending:  # due at b_j = t0 + (j + 1) step when available <= b_j
            end = min(end, (self._pending[0][0] - t0 - 1) // step)
        if self.depth.map is not None and self.depth.t_us is not None:
            # step j reads the map at its start t0 + j step, expired beyond the maximum age
            age_us = self.config.max_depth_age_ms * 1e3
            end = min(end, math.floor((self.depth.t_us + age_us - t0) / step) + 1)
        return end

    def _step_run(self, t0: int, k: int, end: int, flows: _StepFlows,
                  poly: SilhouettePolygon, pose: np.ndarray) -> int | None:
        """Steps ``k..end-1`` of the group starting at ``t0`` (see :meth:`_quiet_end`) with the
        filters' compiled runs (:meth:`VelocityKF.forward_run
        <evtrack.filters.VelocityKF.forward_run>`, :meth:`PoseTimeline.step_run
        <evtrack.tracking.pose_timeline.PoseTimeline.step_run>`): the same states, outputs and
        counts as
        step by step, a few calls instead of a few dozen per step.

        Returns:
            The next step to do: ``end``, or earlier when the object is lost at a step of the
            run (the steps after it are left to the step loop) or a velocity update needs the
            torch path (that step is left to it); ``None``, with nothing done, where the
            compiled runs do not apply.
        """
        cfg = self.config
        st = self.stats
        step = cfg.velocity_step_us
        with _Timer(st.time_s, "velocity"):
            bounds = flows.bounds[k:end + 1]
            lo = int(bounds[0])
            z, missing = self._run_depth(flows, k, end, poly, pose)
            normal = flows.normal[lo:int(bounds[-1])]
            twists = self.vkf.forward_run(
                [step * 1e-6] * (end - k), bounds - lo, torch.from_numpy(flows.uv[lo:bounds[-1]]),
                torch.from_numpy(z), flows.flow[lo:int(bounds[-1])],
                normal if cfg.use_flow_normal_flags else None)
            if twists is None:
                return None
            done = k + len(twists)
            if done == k:
                return k
        with _Timer(st.time_s, "pose"):
            ends = [t0 + (j + 1) * step for j in range(k, done)]
            states = self.timeline.step_run(ends, twists)
            if states is not None:
                tq = torch.cat([states[0][:, 0], states[1][:, 0]], 1).numpy()  # a new array
            else:  # the pose filter's compiled run does not apply (sigma points...): per step
                rows_tq = []
                for b, twist in zip(ends, twists, strict=True):
                    self.timeline.step(b, twist)
                    rows_tq.append(self.ukf.t.tolist()[0] + self.ukf.q.tolist()[0])
                tq = np.array(rows_tq, np.float64).reshape(len(ends), 7)
            # the steps whose silhouette is whole in view (_check_view's common case: visible
            # 1.0, never below min_visible_fraction, which the config keeps in [0, 1]), at once
            in_view = self.silhouette.boxes_in_image(tq[:, :3], tq[:, 3:])
            lost = False
            for n, b in enumerate(ends):
                if in_view[n]:
                    self._out_of_view_us = 0
                else:
                    self._t = b
                    if self._check_view(b, tq[n, :3].tolist(), tq[n, 3:].tolist()):
                        lost = True  # _lose set the held pose; the later steps: the step loop
                        break
            m = n + 1  # the steps counted here; the last one lost when ``lost``
            tracked = m - 1 if lost else m
            self._out_t.extend(ends[:tracked])
            self._out_tq.extend(tq[:tracked])  # rows as views: tq is new, not written again
            self._out_twist.extend(twists[:tracked, 0].numpy().copy())
            self._out_status.extend([STATUS_TRACKING] * tracked)
            per_step = np.diff(bounds[:m + 1])  # RoI flows of each step
            st.steps += m
            st.roi_flows += int(per_step.sum())
            st.velocity_updates += int(np.count_nonzero(per_step))
            st.depth_fallbacks += int(missing[:int(bounds[m]) - lo].sum())
            self._t = ends[m - 1]
            if lost:
                self._record(ends[m - 1])
                return k + m
            self._held = None  # tracking: no held pose
        return done

    def _flow_update(self, ev: Events, t_end: int, search: Tensor | None) -> FlowResult:
        """The flow of a step group's events (its windows all end by ``t_end``).

        After an event burst the flow's burst filter is re-synchronised: the burst's events
        were taken out, so each pixel's first event after it would start a burst even in the
        middle of an edge's, and these onsets, nearly simultaneous along the edges, pair into
        spurious fast flows (a 20 ms burst on a 128x96 sequence: ω_z of -24 to -38 rad/s for
        a few ms after it). For ``flow.refractory_us`` after the burst, the span in which a
        taken-out event could still hold back a later one, the first event of each pixel
        is taken as the continuation of a burst
        (:meth:`TripletFlow.continue_bursts <evtrack.flow.TripletFlow.continue_bursts>`)."""
        span = self.flow.config.refractory_us
        carried = self._resync is not None
        windows = [self._resync] if carried else []
        windows += [(end, end + span) for end in self._burst_ends] if span else []
        self._resync = None
        parts, pos = [], 0
        for i, (start, end) in enumerate(windows):
            if i + 1 < len(windows):  # a later burst ends it (its events are taken out)
                end = min(end, windows[i + 1][0])
            if not (i == 0 and carried):  # a new re-sync: no pixel seen yet
                self._resync_seen = np.zeros(self.camera.width * self.camera.height, bool)
            if start >= t_end:  # a burst ending the group: the next group's
                self._resync = (start, end)
                break
            cut = max(pos, int(torch.searchsorted(ev.t, start))) if len(ev) else 0
            if cut > pos:
                parts.append(self.flow.update(ev[pos:cut], until_us=start, search=None
                                              if search is None else search[pos:cut]))
                pos = cut
            hi = int(torch.searchsorted(ev.t, min(end, t_end))) if len(ev) else 0
            pixel = (ev.y[cut:hi].long() * self.camera.width + ev.x[cut:hi].long()).numpy()
            first = np.unique(pixel, return_index=True)[1]  # each pixel's first event
            first = np.sort(first[~self._resync_seen[pixel[first]]])
            self._resync_seen[pixel] = True
            self.flow.continue_bursts(ev[cut:hi][torch.from_numpy(first)])
            if end > t_end:
                self._resync = (start, end)
        parts.append(self.flow.update(ev[pos:], until_us=t_end,
                                      search=None if search is None else search[pos:]))
        return parts[0] if len(parts) == 1 else FlowResult.cat(parts)

    def _in_burst(self, t: np.ndarray, on_object: np.ndarray, poly: SilhouettePolygon, t0: int,
                  t_end: int) -> np.ndarray:
        """(N,) bool: the events of the steps of ``[t0, t_end)`` that are event bursts (see
        the module docstring); counts them."""
        cfg = self.config
        step = cfg.velocity_step_us
        w, h = self.camera.size
        margin = cfg.mask_margin_px
        v = poly.vertices
        area = 0.5 * abs(float(np.dot(v[:, 0], np.roll(v[:, 1], -1))
                               - np.dot(v[:, 1], np.roll(v[:, 0], -1))))
        perimeter = float(np.linalg.norm(v - np.roll(v, -1, 0), axis=1).sum())
        # the mask: the silhouette grown by the margin (Steiner's formula), the part in the image
        mask_area = poly.visible_fraction * (area + perimeter * margin + np.pi * margin ** 2)
        outside = w * h - min(mask_area, w * h)
        none = np.zeros(len(t), bool)
        if outside < _BURST_MIN_OUTSIDE * w * h or not len(t):
            return none
        steps = (t_end - t0) // step
        # the events are time-sorted: each step's are one slice (the first also takes any
        # before t0, the last any from t_end on), counted without a pass over every event
        cuts = [0, *np.searchsorted(t, t0 + step * np.arange(1, steps), side="left").tolist(),
                len(t)]
        off = np.array([(b - a) - np.count_nonzero(on_object[a:b])
                        for a, b in zip(cuts[:-1], cuts[1:], strict=True)], np.float64)
        rate = off / (outside * step * 1e-6)
        burst = rate > cfg.burst_rate_hz
        if not burst.any():
            return none
        hit = np.repeat(burst, np.diff(cuts))
        # the end of each run of burst steps starts a re-synchronisation (_flow_update)
        ends = np.flatnonzero(burst & ~np.append(burst[1:], False)) + 1
        self._burst_ends += (t0 + step * ends).tolist()
        self.stats.burst_steps += int(burst.sum())
        self.stats.events_in_bursts += int((hit & on_object).sum())
        return hit

    def _thin(self, ev: Events, budget: int) -> Events:
        """At most ``budget`` events of a step group, by cells of RoIs (see the module
        docstring): the first ``int(n_cells * _THIN_RATIO ** level)`` cells of the fixed hash
        order, at the thinning level of the last group unless the budget forces a higher one
        or the next lower one fits in ``_THIN_HEADROOM`` of the budget; the other cells'
        events are counted."""
        s = _THIN_CELL_ROIS * self.config.flow.roi_size
        cols = -(-self.camera.width // s)
        n_cells = cols * -(-self.camera.height // s)
        order = getattr(self, "_cell_order", None)
        if order is None or len(order) != n_cells:
            with np.errstate(over="ignore"):
                hashed = np.arange(n_cells, dtype=np.uint64) * _HASH_MULTIPLIER
            order = self._cell_order = np.argsort(hashed, kind="stable")
        cell = (ev.y.numpy().astype(np.int64) // s) * cols + ev.x.numpy().astype(np.int64) // s
        kept = np.concatenate([[0], np.cumsum(np.bincount(cell, minlength=n_cells)[order])])

        def taken_at(level: int) -> int:
            return int(n_cells * _THIN_RATIO ** level)

        def events_at(level: int) -> int:
            return int(kept[taken_at(level)])

        level = self._thin_level
        while level and events_at(level - 1) <= _THIN_HEADROOM * budget:
            level -= 1
        while events_at(level) > budget:  # ends: no cell at all at the last level
            level += 1
        self._thin_level = level
        if level == 0:
            return ev
        taken = np.zeros(n_cells, bool)
        taken[order[:taken_at(level)]] = True
        keep = taken[cell]
        self.stats.events_thinned += int(len(ev) - keep.sum())
        return ev[torch.from_numpy(keep)]

    def _fallback_depth(self, pose: np.ndarray | None) -> float:
        return float(pose[2, 3]) if pose is not None else float("nan")

    def _velocity_step(self, dt: float, flows: _StepFlows, k: int,
                       poly: SilhouettePolygon | None, pose: np.ndarray | None) -> Tensor:
        """VelocityKF predict + update from the RoI flows of step ``k`` of the group; returns
        the twist (1, 6)."""
        uv, flow, normal = flows.step(k)
        if len(uv) == 0 or (poly is None and pose is not None):
            return self.vkf.predict(dt)
        if pose is None:  # before the first pose: plain patch medians, no fallback
            if not isinstance(self.depth, SensorDepth):
                return self.vkf.predict(dt)  # model depth needs a pose (see _remeasure)
            z = self._unranged_depth(uv)
        elif isinstance(self.depth, SensorDepth):
            z = self._step_depth(flows, k, poly, pose)
        else:
            z = self._roi_depth(uv, poly, pose)
        self.stats.roi_flows += len(uv)
        self.stats.velocity_updates += 1
        return self._vkf_update(dt, uv, z, flow, normal)

    def _vkf_update(self, dt: float, uv: np.ndarray, z: np.ndarray, flow: Tensor,
                    normal: Tensor) -> Tensor:
        """One VelocityKF predict + update from (N,) RoIs; returns the twist (1, 6)."""
        kw = {"dtype": self.vkf.twist.dtype, "device": self.device}
        return self.vkf(dt, torch.as_tensor(uv, **kw).unsqueeze(0),
                        torch.as_tensor(z, **kw).unsqueeze(0), flow.unsqueeze(0),
                        normal.unsqueeze(0) if self.config.use_flow_normal_flags else None)

    def _keep_unposed(self, t_end: int, flows: _StepFlows, k: int) -> None:
        """Keep step ``k`` (ending at ``t_end``) of an unposed group for :meth:`_remeasure`,
        and forget the kept steps older than the pose filter's past."""
        uv, flow, normal = flows.step(k)
        depth = ((self.depth.map, self.depth.t_us) if isinstance(self.depth, SensorDepth)
                 else (None, None))
        lo, hi = int(flows.bounds[k]), int(flows.bounds[k + 1])
        self._unposed[t_end] = _UnposedStep(uv, flow, normal, depth, flows.support[lo:hi])
        oldest = t_end - self.timeline.horizon_us
        while self._unposed and next(iter(self._unposed)) <= oldest:
            del self._unposed[next(iter(self._unposed))]

    def _remeasure(self, t_pose: int) -> None:
        """The late pose of ``t_pose`` started the track: measure the kept unposed steps
        after it again, each at the pose the filter has at its start (RoIs inside the
        silhouette, depths in its range, the object's centre as the velocity filter's pivot;
        one pose per step group, as :meth:`_group` has), with the velocity filter started
        afresh at ``t_pose``, and replay the pose filter
        with these twists (see ``TrackerConfig.remeasure_on_pose``)."""
        kept, self._unposed = self._unposed, {}
        cfg = self.config
        if not self._pose_explains_events(t_pose, kept):
            self.stats.remeasures_skipped += 1
            return
        self.vkf.reset(1)
        saved = ((self.depth.map, self.depth.t_us) if isinstance(self.depth, SensorDepth)
                 else None)

        group_us = cfg.velocity_step_us * cfg.flow_batch_steps
        segment_us = cfg.velocity_step_us * min(_SEGMENT_STEPS, cfg.flow_batch_steps)

        def segment(t_us: int) -> tuple[int, int]:  # (group, segment within it) of a step
            return t_us // group_us, t_us % group_us // segment_us

        # the segment's pose and silhouette, as in _group_steps, and its steps' new twists by
        # step end
        at: dict[str, Any] = {"segment": None, "twists": {}}

        def twist_of(t_start: int, t_end: int) -> Tensor:
            if at["segment"] != segment(t_start):
                pose, poly = self._segment_pose()
                at.update(segment=segment(t_start), pose=pose, poly=poly)
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
                at["twists"] = self._remeasure_group(kept, times, poly, pose)
            twist = at["twists"].pop(t_end, None)
            if twist is None:
                raise RuntimeError(f"Tracker._remeasure: step ({t_start}, {t_end}] µs was not "
                                   "among its group's steps")
            return twist

        if isinstance(self.depth, ModelDepth):
            self.depth.invalidate()  # rendered again at the replayed poses and times
        try:
            with _Timer(self.stats.time_s, "velocity"):
                self.timeline.remeasure(t_pose, twist_of)
        finally:
            if saved is not None:
                self.depth.map, self.depth.t_us = saved
            elif isinstance(self.depth, ModelDepth):
                self.depth.invalidate()  # the live steps render at the present pose

    def _remeasure_group(self, kept: dict[int, _UnposedStep], times: list[int],
                         poly: SilhouettePolygon | None, pose: np.ndarray
                         ) -> dict[int, Tensor]:
        """The new twists (1, 6) of the steps ``(times[i], times[i + 1]]`` of one step group
        of :meth:`_remeasure`, by step end: the kept RoIs inside the group's silhouette, their
        depths at the group's pose from each step's depth frame, then the velocity filter,
        by one compiled run where it applies (:meth:`VelocityKF.forward_run
        <evtrack.filters.VelocityKF.forward_run>`) or step by step: the same twists either
        way. A step without RoIs inside only predicts."""
        cfg = self.config
        n = len(times) - 1
        dts = [(times[i + 1] - times[i]) * 1e-6 for i in range(n)]
        steps = [kept.get(t_end) for t_end in times[1:]]
        if poly is not None:
            rows = [i for i, step in enumerate(steps) if step is not None and len(step.uv)]
        else:
            rows = []
        empty = np.zeros((0, 2))
        uv = [empty] * n
        flow: list[Tensor | None] = [None] * n
        normal: list[Tensor | None] = [None] * n
        if rows:  # one silhouette test for the group's RoIs
            inside = np.split(poly.contains(np.concatenate([steps[i].uv for i in rows]),
                                            cfg.mask_margin_px),
                              np.cumsum([len(steps[i].uv) for i in rows])[:-1])
            for i, keep in zip(rows, inside, strict=True):
                if keep.any():
                    step = steps[i]
                    uv[i] = step.uv[keep]
                    sel = torch.from_numpy(keep)
                    flow[i] = step.flow[sel.to(step.flow.device)]
                    normal[i] = step.normal[sel.to(step.normal.device)]
        z = self._remeasure_depths(steps, times, uv, poly, pose)
        measured = [i for i in range(n) if len(uv[i])]
        self.stats.steps_remeasured += len(measured)
        twists: list[Tensor] = []
        if measured and self.step_runs:
            bounds = np.concatenate([[0], np.cumsum([len(u) for u in uv])])
            run = self.vkf.forward_run(
                dts, bounds, torch.from_numpy(np.concatenate(uv)),
                torch.from_numpy(np.concatenate(z)), torch.cat([flow[i] for i in measured]),
                torch.cat([normal[i] for i in measured]) if cfg.use_flow_normal_flags else None)
            if run is not None:
                twists = list(run.unbind(0))
        for i in range(len(twists), n):  # step by step (the rest after a failed run)
            if len(uv[i]):
                twists.append(self._vkf_update(dts[i], uv[i], z[i], flow[i], normal[i]))
            else:
                twists.append(self.vkf.predict(dts[i]))
        return dict(zip(times[1:], twists, strict=True))

    def _remeasure_depths(self, steps: list[_UnposedStep | None], times: list[int],
                          uv: list[np.ndarray], poly: SilhouettePolygon | None,
                          pose: np.ndarray) -> list[np.ndarray]:
        """The depths (m) of the RoIs ``uv[i]`` of the steps of a :meth:`_remeasure_group`,
        each read from its own step's sensor depth frame at the step's start (rendered at the
        group's pose for model depth), missing ones by the fallback (counted): one lookup per
        run of steps reading the same frame, the same depths as one per step."""
        z = [np.zeros(0)] * len(uv)
        measured = [i for i in range(len(uv)) if len(uv[i])]
        sensor = isinstance(self.depth, SensorDepth)
        max_age_us = self.config.max_depth_age_ms * 1e3

        def frame(i: int) -> tuple[Any, ...]:
            if not sensor:
                return (i,)  # model depth: rendered per step
            depth_map, t_us = steps[i].depth
            stale = t_us is not None and times[i] - t_us > max_age_us
            return (id(depth_map), t_us, stale)

        for _, same_frame in groupby(measured, key=frame):
            run = list(same_frame)
            if sensor:
                self.depth.map, self.depth.t_us = steps[run[0]].depth
            both = self._roi_depth(np.concatenate([uv[i] for i in run]), poly, pose,
                                   t_now=times[run[0]])
            for i, part in zip(run, np.split(both, np.cumsum([len(uv[i]) for i in run])[:-1]),
                               strict=True):
                z[i] = part
        return z

    def _pose_explains_events(self, t_pose: int, kept: dict[int, _UnposedStep]) -> bool:
        """Whether at least ``remeasure_min_inside`` of the kept RoI flows (of at least
        ``_REMEASURE_CHECK_MIN_SUPPORT`` supporting events) of the ``_REMEASURE_CHECK_US``
        after ``t_pose`` lie in the silhouette (with the mask margin) at the timeline's pose
        of their step (carried from the pose by the unposed twists; with model depth, held
        still: only the steps up to the first ``_REMEASURE_CHECK_MODEL_ROIS`` such RoI flows);
        True when they are fewer than ``_REMEASURE_CHECK_MIN_ROIS``. Measured again at a
        wrong pose, the steps lose their RoIs and take depths out of the object's range, which
        carries the wrong pose further off than the unposed twists do."""
        inside = total = 0
        held_still = not isinstance(self.depth, SensorDepth)
        for t_end, step in kept.items():  # in time order (kept as the steps ran)
            if not t_pose < t_end <= t_pose + _REMEASURE_CHECK_US or not len(step.uv):
                continue
            if held_still and total >= _REMEASURE_CHECK_MODEL_ROIS:
                break
            pose = self._past_pose(t_end)
            if pose is None:
                continue
            uv = step.uv[step.support >= _REMEASURE_CHECK_MIN_SUPPORT]
            poly = self.silhouette.polygon(pose) if np.isfinite(pose).all() else None
            total += len(uv)
            if poly is not None and len(uv):
                inside += int(poly.contains(uv, self.config.mask_margin_px).sum())
        if total < _REMEASURE_CHECK_MIN_ROIS:
            return True
        return inside / total >= self.config.remeasure_min_inside

    def _unranged_depth(self, uv: np.ndarray) -> np.ndarray:
        self._expire_sensor_depth(self._t)
        return self.depth.lookup(uv, None)

    def _step_depth(self, flows: _StepFlows, k: int, poly: SilhouettePolygon,
                    pose: np.ndarray) -> np.ndarray:
        """:meth:`_roi_depth` of step ``k``'s RoIs (sensor depth), from :meth:`_run_depth`."""
        z, missing = self._run_depth(flows, k, k + 1, poly, pose)
        self.stats.depth_fallbacks += int(missing.sum())
        return z

    def _run_depth(self, flows: _StepFlows, k: int, end: int, poly: SilhouettePolygon,
                   pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The sensor depths (m) of the RoIs of steps ``k..end-1`` (the map read at step
        ``k``'s start), the missing ones replaced by the fallback (not counted), and which
        were missing. One lookup serves the rows of every remaining step of the group while
        the depth map stays the same (the group's silhouette and pose are fixed; a new or
        expired map starts a new lookup): the same depths as step by step at a fraction of
        the per-call cost."""
        self._expire_sensor_depth(self._t)
        lo, hi = int(flows.bounds[k]), int(flows.bounds[end])
        cache = flows.depth_cache
        if cache is None or cache[0] is not self.depth.map or cache[3] is not poly:
            z_lo, z_hi = poly.z_range
            cache = (self.depth.map, lo, self.depth.lookup(
                flows.uv[lo:], (z_lo - _DEPTH_TOLERANCE_M, z_hi + _DEPTH_TOLERANCE_M)), poly)
            flows.depth_cache = cache
        z = cache[2][lo - cache[1]:hi - cache[1]].copy()
        return z, self._fill_missing(z, pose)

    def _fill_missing(self, z: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Replace the missing depths (NaN) of ``z`` (N,) metres, in place, by the fallback
        (the predicted depth of the object's origin); returns which were missing (N,)."""
        missing = ~np.isfinite(z)
        if missing.any():
            z[missing] = self._fallback_depth(pose)
        return missing

    def _with_fallback(self, z: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """``z`` (N,) metres with its missing depths replaced by the fallback
        (:meth:`_fill_missing`), counted in the stats; changes ``z``."""
        self.stats.depth_fallbacks += int(self._fill_missing(z, pose).sum())
        return z

    def _expire_sensor_depth(self, t_now: int) -> None:
        """Drop a sensor depth frame older than ``max_depth_age_ms`` (lookups then fall back)."""
        if (self.depth.t_us is not None
                and t_now - self.depth.t_us > self.config.max_depth_age_ms * 1e3):
            self.depth.map = None

    def _roi_depth(self, uv: np.ndarray, poly: SilhouettePolygon, pose: np.ndarray,
                   t_now: int | None = None, patch: bool = True) -> np.ndarray:
        t_now = self._t if t_now is None else t_now
        if isinstance(self.depth, ModelDepth):
            self.depth.update(t_now, pose)
        else:
            self._expire_sensor_depth(t_now)  # too old: fall back
        z_lo, z_hi = poly.z_range
        z = self.depth.lookup(uv, (z_lo - _DEPTH_TOLERANCE_M, z_hi + _DEPTH_TOLERANCE_M), patch)
        return self._with_fallback(z, pose)

    # ------------------------------------------------------------------ measurements
    def _apply_due(self, t_now: int) -> None:
        while self._pending and self._pending[0][0] <= t_now:
            available, _, item = heapq.heappop(self._pending)
            if isinstance(item, PoseMeasurement):
                self._fuse_pose(item)
            elif isinstance(item, _DepthFrame):
                self._fuse_range(item)
                self._fuse_alignment(item)
            elif isinstance(item, _Miss):
                self._on_miss(t_now)
            elif isinstance(item, _PoseCall):
                self._take_pose_call(item, available, t_now)
            else:
                self._fuse_twist(*item)

    def _on_miss(self, t_now: int) -> None:
        self._misses += 1
        limit = self.config.lost_after_misses
        if limit and self._misses >= limit and self.initialized:
            self._lose(t_now)

    def _plausible_alternative(self, m: PoseMeasurement) -> PoseMeasurement | None:
        """The first of ``m``'s alternatives (most confident first) at or above
        ``pose_min_confidence`` and ``pose_alternatives_min_confidence`` that passes the depth
        check, aligned as it checked; ``None`` without one or with ``pose_alternatives`` off."""
        c = self.config
        if not c.pose_alternatives:
            return None
        least = max(c.pose_min_confidence, c.pose_alternatives_min_confidence)
        for alt in m.alternatives:
            if alt.confidence < least:
                continue
            checked = self._depth_checked(alt)
            if checked is not None:
                self.stats.poses_from_alternatives += 1
                return checked
        return None

    def _fuse_pose(self, m: PoseMeasurement) -> None:
        checked = self._depth_checked(m)
        if checked is None:
            checked = self._plausible_alternative(m)
        if checked is None:
            self.stats.poses_implausible += 1  # neither a found pose nor a miss
            return
        m = checked
        self._misses = 0
        if self.method == "velocity" and self.initialized:
            return  # the velocity baseline uses poses only to (re-)initialise
        turned_back = False  # the track deemed half a turn off: re-initialise on m
        if self.half_turns is not None and self.initialized:
            m, turned_back = self._nearer_half_turn(m)
        rejected = int(self.ukf.rejected[0])
        reinit = int(self.ukf.reinitialised[0])
        t, q = pose_measurement_value(m.pose, self.ukf.t.dtype, self.device)
        cov = None if m.cov is None else m.cov.to(self.ukf.t.dtype).to(self.device).unsqueeze(0)
        if m.t_us > self.timeline.now:  # pragma: no cover - _apply_due never lets it happen
            raise RuntimeError(f"pose at {m.t_us} µs applied before the clock reached it")
        was_init = self.initialized
        kind = ("pose_reinit" if turned_back or self._agrees_with_rejected(m.t_us, m.pose)
                else "pose")
        if not self.timeline.add(m.t_us, kind, (t, q), cov):
            self.stats.poses_late += 1
            return
        newly_rejected = int(self.ukf.rejected[0]) - rejected
        newly_reinit = int(self.ukf.reinitialised[0]) - reinit
        self.stats.poses_rejected += max(0, newly_rejected)
        self.stats.reinitialisations += max(0, newly_reinit)
        self._rejected_pose = ((m.t_us, m.pose) if newly_rejected > 0 and newly_reinit <= 0
                               else None)
        if self.initialized and not was_init:
            self._out_of_view_us = 0
            if self.method == "frame-flow":
                self._replay_frame_flow(m.t_us)
            elif self._unposed:
                self._remeasure(m.t_us)

    def _nearer_half_turn(self, m: PoseMeasurement) -> tuple[PoseMeasurement, bool]:
        """``m``, or its half turn about one of ``pose_half_turn_axes`` where that lies nearer
        the filter's pose at ``m.t_us`` (see :mod:`evtrack.tracking.pose_flips`); and whether the
        filter is to re-initialise on ``m`` as it is instead: the pose is the
        ``pose_half_turn_reinit_after``-th in a row to need the turn, so the track, not the
        network, is deemed half a turn off (it started on a turned pose)."""
        reference = self._past_pose(m.t_us)
        if reference is None:
            return m, False
        pose = m.pose.detach().cpu().numpy().astype(np.float64)
        chosen, axis = self.half_turns.resolve(pose, reference)
        if axis is None:
            self._half_turns_in_row = 0
            return m, False
        self._half_turns_in_row += 1
        limit = self.config.pose_half_turn_reinit_after
        if limit and self._half_turns_in_row >= limit:
            self._half_turns_in_row = 0
            self.stats.half_turn_reinits += 1
            return m, True
        self.stats.poses_half_turned += 1
        return dataclasses.replace(m, pose=torch.as_tensor(chosen, dtype=m.pose.dtype)), False

    def _agrees_with_rejected(self, t_us: int, pose: Tensor) -> bool:
        """Whether the previous pose was rejected by the gate and ``pose`` lies within the
        motion the config allows since (``reinit_agree_*``): two poses that agree with each
        other but not with the filter mean the filter is off, so the second re-initialises
        it. Random outliers rarely agree with each other."""
        c = self.config
        if not c.reinit_on_agreement or self._rejected_pose is None or not self.initialized:
            return False
        t0, pose0 = self._rejected_pose
        dt = max(0.0, (t_us - t0) * 1e-6)
        moved = float(position_errors(pose, pose0))
        turned = math.degrees(float(rotation_errors(pose, pose0)))
        return (moved <= c.reinit_agree_m + c.reinit_agree_m_per_s * dt
                and turned <= c.reinit_agree_deg + c.reinit_agree_deg_per_s * dt)

    def _fuse_range(self, frame: _DepthFrame) -> None:
        """Measure the object's range on a depth frame at the filter's pose of the frame's
        time and fuse it there (see :mod:`evtrack.tracking.depth_range`)."""
        if not self.initialized or self.depth_range is None:
            return
        with _Timer(self.stats.time_s, "depth_range"):
            T_ev = self._past_pose(frame.t_us)
            if T_ev is None:
                return
            T_d = self._T_depth_event @ T_ev
            res = self.depth_range.measure(frame.depth, T_d)
            if not res.ok:
                skipped = self.stats.depth_ranges_skipped
                skipped[res.reason] = skipped.get(res.reason, 0) + 1
                return
            # uᵀ t_d = d with t_d = R t_ev + p  <=>  (Rᵀ u)ᵀ t_ev = d - uᵀ p
            R, p = self._T_depth_event[:3, :3], self._T_depth_event[:3, 3]
            u_ev = R.T @ res.direction
            d_ev = res.distance - float(res.direction @ p)
            kw = {"dtype": self.ukf.t.dtype, "device": self.device}
            value = (torch.as_tensor(u_ev, **kw).reshape(1, 3),
                     torch.tensor([d_ev], **kw))
            if self.timeline.add(frame.t_us, "range", value,
                                 torch.tensor([res.variance], **kw)):
                self.stats.depth_ranges += 1

    def _fuse_alignment(self, frame: _DepthFrame) -> None:
        """Align the mesh with a depth frame from the filter's pose of the frame's time and
        fuse the aligned pose there with the fit's covariance (``depth_icp``)."""
        if not self.initialized or self.depth_icp is None:
            return
        cfg = self.config
        period_us = 1e6 / cfg.depth_icp_rate_hz
        last = self._last_alignment_us
        if last is not None and 0 <= frame.t_us - last < 0.9 * period_us:
            return
        with _Timer(self.stats.time_s, "depth_icp"):
            T_ev = self._past_pose(frame.t_us)
            if T_ev is None:
                return
            self._last_alignment_us = frame.t_us
            T_d = self._T_depth_event @ T_ev
            res = self.depth_icp.refine(T_d, frame.depth, self._depth_K, self._depth_dist)
            if not res.refined:
                skipped = self.stats.depth_alignments_skipped
                skipped[res.refusal] = skipped.get(res.refusal, 0) + 1
                return
            cov_d = _alignment_covariance(res, cfg.depth_icp_std_m,
                                          math.radians(cfg.depth_icp_std_deg))
            A = self._T_event_depth
            T_meas = A @ res.pose
            Ra = np.kron(np.eye(2), A[:3, :3])  # both tangent blocks rotate with the frame
            kw = {"dtype": self.ukf.t.dtype, "device": self.device}
            value = pose_measurement_value(torch.from_numpy(T_meas), kw["dtype"], kw["device"])
            cov = torch.as_tensor(Ra @ cov_d @ Ra.T, **kw).reshape(1, 6, 6)
            if self.timeline.add(frame.t_us, "aligned", value, cov):
                self.stats.depth_alignments += 1

    def _fuse_twist(self, t_us: int, twist: Tensor, cov: Tensor) -> None:
        if not self.initialized:
            return
        if self.timeline.add(t_us, "twist", (twist,), cov):
            self.stats.twist_measurements += 1

    # ------------------------------------------------------------------ frame-flow
    def _frame_flow(self, t_us: int, rgb: np.ndarray) -> None:
        """Dense flow from the previous frame -> one twist measurement (event camera frame).

        While no pose has started the track, frame pairs are kept for ``history_ms`` (with the
        depth frame of their time): the pose that starts it arrives ``pose_latency_ms`` after
        its frame was taken, and the pairs since that frame are measured then, each at the pose
        the timeline gives for its time (:meth:`_replay_frame_flow`), as the event flow carries
        a late first pose to the present in the full method.
        """
        pair = self.dense_flow.push(t_us, rgb)
        if pair is None:
            return
        if not self.initialized:
            depth = ((self.depth.map, self.depth.t_us) if isinstance(self.depth, SensorDepth)
                     else None)
            self._ff_backlog.append((pair, depth))
            horizon = t_us - self.config.history_ms * 1e3
            while self._ff_backlog and self._ff_backlog[0][0].t0_us < horizon:
                self._ff_backlog.popleft()
            return
        measured = self._measure_frame_pair(pair, self.pose(pair.t0_us), t_us)
        if measured is not None:
            dtype = self.ukf.t.dtype
            V_ev, cov_ev = measured
            self._schedule(t_us, (pair.t_mid_us, V_ev.to(dtype), cov_ev.to(dtype)))
            self._apply_due(self._t)

    def _measure_frame_pair(self, pair, pose_ev: np.ndarray, t_us: int
                            ) -> tuple[Tensor, Tensor] | None:
        """The twist (1, 6) and its covariance (1, 6, 6), event camera frame, that the dense
        flow of ``pair`` measures for the object at ``pose_ev`` (at the pair's first frame);
        ``None`` when no flow sample falls on the object."""
        if not np.isfinite(pose_ev).all():
            return None
        pose_rgb = (self.T_rgb_event @ torch.from_numpy(pose_ev)).numpy()
        poly = self.rgb_silhouette.polygon(pose_rgb)
        if poly is None:
            return None
        cfg = self.config.frame_flow
        pts = grid_in_polygon(poly, pair.flow.shape[:2], cfg.grid_px, cfg.max_samples)
        if len(pts) == 0:
            return None
        uv, flow = pair.sample(pts)
        z = self._roi_depth(pts.astype(np.float64), poly, pose_rgb, t_now=t_us)
        kw = {"dtype": self.frame_kf.twist.dtype, "device": self.device}
        self.frame_kf.reset(1)
        V = self.frame_kf.update(torch.as_tensor(uv, **kw).unsqueeze(0),
                                 torch.as_tensor(z, **kw).unsqueeze(0),
                                 torch.as_tensor(flow, **kw).unsqueeze(0),
                                 torch.zeros(1, len(uv), dtype=torch.bool, device=self.device))
        A = self.rgb_to_event_twist.to(**kw)
        return (A @ V[0]).unsqueeze(0), (A @ self.frame_kf.cov[0] @ A.T).unsqueeze(0)

    def _past_pose(self, t_us: int) -> np.ndarray | None:
        """(4, 4) the pose the filter had at a kept past time (:meth:`PoseTimeline.pose_at`),
        or ``None``."""
        tq = self.timeline.pose_at(t_us)
        return None if tq is None else _quat_to_matrix(tq[0].tolist(), tq[1].tolist())

    def _replay_frame_flow(self, t_start: int) -> None:
        """Measure the kept frame pairs from ``t_start`` (the pose that started the track) to
        now, in order, each at the timeline's pose for its first frame."""
        dtype = self.ukf.t.dtype
        backlog, self._ff_backlog = self._ff_backlog, deque()
        for pair, depth in backlog:
            if pair.t0_us < t_start or pair.t_mid_us > self.timeline.now:
                continue
            pose_ev = self._past_pose(pair.t0_us)
            if pose_ev is None:
                continue
            saved = None
            if depth is not None and isinstance(self.depth, SensorDepth):
                saved = (self.depth.map, self.depth.t_us)
                self.depth.map, self.depth.t_us = depth
            try:
                measured = self._measure_frame_pair(pair, pose_ev, pair.t1_us)
            finally:
                if saved is not None:
                    self.depth.map, self.depth.t_us = saved
            if measured is not None and self.timeline.add(
                    pair.t_mid_us, "twist", (measured[0].to(dtype),), measured[1].to(dtype)):
                self.stats.twist_measurements += 1
                self.stats.twists_replayed += 1

    # ------------------------------------------------------------------ loss and output
    def _check_view(self, t1: int, t: list[float] | None = None,
                    q: list[float] | None = None) -> bool:
        """Count the step ending at ``t1`` out of view, or not, at the pose ``t`` (3,), ``q``
        (4,) (default: the pose filter's); lose the object after ``lost_after_ms`` out of
        view. Returns whether it was lost here."""
        if not self.initialized:
            return False
        if t is None or q is None:
            t, q = self.ukf.t.tolist()[0], self.ukf.q.tolist()[0]
        if self.silhouette.box_in_image(t, q):
            visible = 1.0  # the whole silhouette in view (the common case: no polygon)
        else:
            visible = self.silhouette.visible_fraction(_quat_to_matrix(t, q))
        if visible >= self.config.min_visible_fraction:
            self._out_of_view_us = 0
            return False
        self._out_of_view_us += self.config.velocity_step_us
        if self._out_of_view_us >= self.config.lost_after_ms * 1e3:
            self._lose(t1, _quat_to_matrix(t, q))
            return True
        return False

    def _lose(self, t_now: int, held: np.ndarray | None = None) -> None:
        """The object is lost: hold the last pose (``held``, default the pose filter's),
        forget the filters' states."""
        self._held = self._current_pose() if held is None else held
        self._ever_lost = True
        self.stats.lost += 1
        self._out_of_view_us = 0
        self._rejected_pose = None
        self._half_turns_in_row = 0
        self.ukf.reset(1)
        self.vkf.reset(1)
        self.timeline.start(t_now)
        if self.method == "ge":
            self.ge.reset()

    def _record(self, t1: int) -> None:
        status = self.status
        if status == STATUS_TRACKING:
            tq = np.array(self.ukf.t.tolist()[0] + self.ukf.q.tolist()[0])
            self._held = None
        elif status == STATUS_LOST and self._held is not None:
            t, q = matrix_to_tq(torch.from_numpy(self._held))
            tq = np.concatenate([t.numpy(), q.numpy()])
        else:
            tq = np.full(7, np.nan)
        self._out_t.append(t1)
        self._out_tq.append(tq.astype(np.float64))
        self._out_twist.append(self._current_twist() if status == STATUS_TRACKING
                               else np.zeros(6))
        self._out_status.append(status)

    def trajectory(self) -> Trajectory:
        """Every output so far: one sample at the end of each velocity step."""
        from evtrack.geometry import tq_to_matrix

        n = len(self._out_t)
        tq = torch.from_numpy(np.asarray(self._out_tq, np.float64).reshape(n, 7))
        poses = torch.full((n, 4, 4), float("nan"), dtype=torch.float64)
        ok = torch.isfinite(tq).all(1)
        if ok.any():
            poses[ok] = tq_to_matrix(tq[ok, :3], tq[ok, 3:])
        meta = {"config": self.config.to_dict(), "stats": self.stats.to_dict()}
        return Trajectory(torch.tensor(self._out_t, dtype=torch.int64), poses,
                          torch.from_numpy(np.asarray(self._out_twist, np.float64).reshape(n, 6)),
                          torch.tensor(self._out_status, dtype=torch.int8), self.method, meta)

    def pose(self, t_us: int | None = None) -> np.ndarray:
        """The pose (4, 4) at ``t_us`` (default: now).

        For a past time, the output of the last step ending at or before it, moved on by that
        step's twist; for a time after the clock, the current pose predicted with the current
        twist. NaN before the first pose.
        """
        twist, T, t_ref = self._lookup(t_us)
        if not np.isfinite(T).all():
            return T
        dt = (t_us - t_ref) * 1e-6 if t_us is not None else 0.0
        if dt == 0:
            return T
        return moved_pose(T, twist, dt)

    def twist(self, t_us: int | None = None) -> np.ndarray:
        """The twist (6,) ``[v_o, ω]`` at ``t_us`` (default: now); see :meth:`pose`."""
        return self._lookup(t_us)[0]

    def _lookup(self, t_us: int | None) -> tuple[np.ndarray, np.ndarray, int]:
        if self._t is None:
            return np.zeros(6), np.full((4, 4), np.nan), 0
        if t_us is None or t_us >= self._t or not self._out_t:
            if self.status == STATUS_TRACKING:
                return self._current_twist(), self._current_pose(), self._t
            held = self._held if self._held is not None else np.full((4, 4), np.nan)
            return np.zeros(6), held, self._t
        i = int(np.searchsorted(np.asarray(self._out_t), int(t_us), side="right")) - 1
        if i < 0:
            return np.zeros(6), np.full((4, 4), np.nan), int(t_us)
        tq = self._out_tq[i]
        T = _quat_to_matrix(tq[:3], tq[3:]) if np.isfinite(tq).all() else np.full((4, 4), np.nan)
        return self._out_twist[i].copy(), T, self._out_t[i]

    # ------------------------------------------------------------------ offline
    def track(self, sequence, progress: bool = False) -> Trajectory:
        """Track a whole :class:`~evtrack.Sequence` (events and frames in time order).

        The pose source runs on the frames at ``pose_rate_hz`` and its poses reach the filter
        ``pose_latency_ms`` later, as they would live.

        Returns:
            the :class:`~evtrack.tracking.trajectory.Trajectory` (one sample per velocity step).
        """
        threads = torch.get_num_threads()
        if self.config.torch_threads > 0:
            torch.set_num_threads(threads_per_job(self.config.torch_threads))
        self._async_poses = self.config.pose_async
        try:
            with self._blas:  # the worker's pose calls all end inside (flush settles them)
                return self._track(sequence, progress)
        finally:
            self._async_poses = False
            torch.set_num_threads(threads)

    def _read_prepared(self, sequence, depth_times: list[int], index: int) -> _PreparedDepth:
        """Depth frame ``index`` of ``sequence`` and its event-camera map (run in the reader
        thread: :meth:`SensorDepth.prepare` reads no state)."""
        raw = sequence.depth(index)
        return _PreparedDepth(raw, self.depth.prepare(depth_times[index], raw))

    def _track(self, sequence, progress: bool) -> Trajectory:
        self.reset()
        rgb_t = sequence.rgb_times_us.tolist()
        depth_t = sequence.depth_times_us.tolist()
        depth_index = {t: i for i, t in enumerate(depth_t)}
        rgb_index = {t: i for i, t in enumerate(rgb_t)}
        frame_times = sorted(set(rgb_t) | set(depth_t))
        events = sequence.iter_events(window_us=_EVENTS_CHUNK_US)
        carry: Events | None = None
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=len(frame_times), unit="frame", desc=f"track {self.method}")

        def push_until(t_stop: int | None) -> None:
            nonlocal carry
            while True:
                chunk = carry if carry is not None else next(events, None)
                carry = None
                if chunk is None:
                    return
                if t_stop is None:
                    self.push_events(chunk)
                    continue
                k = int(torch.searchsorted(chunk.t, torch.tensor([t_stop]))[0])
                if k:
                    self.push_events(chunk[:k])
                if k < len(chunk):
                    carry = chunk[k:]
                    return

        # the sensor depth is read at every depth frame: decode and prepare the next one in a
        # worker thread while this one is used (same frames and maps, made sooner)
        read_depth = (_Prefetched(lambda i: self._read_prepared(sequence, depth_t, i),
                                  len(depth_t))
                      if isinstance(self.depth, SensorDepth) and len(depth_t) > 1
                      else sequence.depth)
        try:
            for t in frame_times:
                push_until(t)
                i_rgb, i_d = rgb_index.get(t), depth_index.get(t)
                rgb = (lambda i=i_rgb: sequence.rgb(i)) if i_rgb is not None else None
                depth = (lambda i=i_d: read_depth(i)) if i_d is not None else None
                self.push_frame(t, rgb, depth)
                if bar is not None:
                    bar.update(1)
            # frames are read when the steps reach them: the last ones only in the final
            # step groups, so the reader stays open until the stream is done
            push_until(None)
            if self._last_event_t is not None:
                self.advance(self._last_event_t + 1)
            self.flush()
        finally:
            if isinstance(read_depth, _Prefetched):
                read_depth.close()
        if bar is not None:
            bar.close()
        return self.trajectory()
