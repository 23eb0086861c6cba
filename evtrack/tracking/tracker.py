"""``Tracker``: 6-DoF pose tracking from events and RGB-D frames (the method paper, Sec. III).

Data flow of the ``full`` method (docs/architecture.md), once per velocity step (1 ms by default)::

    events of the step ──► event gate: kept if within mask_margin_px of the predicted silhouette
        ──► TripletFlow (one flow window per step) ──► RoI flows (px/s)
        ──► depth at the RoIs (sensor depth frame or mesh rendered at the predicted pose)
        ──► VelocityKF (decaying-velocity predict + flow update) ──► twist [v_o, ω]
        ──► PoseUKF.predict(twist, step)  (+ the velocity bias it learns from the poses)
    RGB frames at pose_rate_hz ──► pose source ──► pose available at t + pose_latency
        ──► pose gate ──► PoseUKF.update at the frame's time t (the filter rolls back and replays)

The tracker is a facade over parts with one job each: the clock and input queues
(:mod:`~evtrack.tracking.inputs`), the step scheduler (:mod:`~evtrack.tracking.scheduler`),
the event gate (:mod:`~evtrack.tracking.event_gate`), the load controller
(:mod:`~evtrack.tracking.load_control`), the motion source picked by ``method``
(:mod:`~evtrack.tracking.motion`), RoI depth (:mod:`~evtrack.tracking.roi_depth`), the pose
calls and gate (:mod:`~evtrack.tracking.pose_calls`, :mod:`~evtrack.tracking.pose_gate`), the
depth fusions (:mod:`~evtrack.tracking.depth_fusion`) and the outputs
(:mod:`~evtrack.tracking.outputs`).

The methods (``TrackerConfig.method``, one motion source each):

* ``full``: as above (the paper), with one addition by default: the pose filter learns a bias
  of the twist's velocity that grows with the object's speed from the pose innovations
  (``pose_ukf.velocity_bias``; the twists the tracker outputs are the velocity filter's,
  without it).
* ``velocity``: the same velocity pipeline; poses are used only to initialise (and to
  re-initialise after the object was lost).
* ``pose``: no velocity; the pose UKF (``pose_only_ukf``, random-walk process noise) with poses.
* ``frame-flow``: ROFT-like dense RGB flow -> twist measurements of a constant-velocity pose
  UKF (:mod:`evtrack.tracking.baselines.frame_flow_motion`).
* ``ge``: the 1-DoF generative event model in place of the flow
  (:mod:`evtrack.tracking.baselines.ge_motion`).
* any name registered with :func:`evtrack.tracking.motion.register_motion_source`.

In :meth:`Tracker.track` the pose source runs in a worker thread meanwhile (``pose_async``):
its result is only taken when it becomes available, so the trajectory is the same.

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
(:class:`~evtrack.filters.PoseUKF`), and on the pose gate's verdict
(:mod:`evtrack.tracking.pose_gate`).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from functools import singledispatchmethod
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.config_values import checked_device
from evtrack.errors import ConfigError, EventsError
from evtrack.events import Events
from evtrack.geometry import matrix_to_tq

# evtrack.models is imported here, not where depth_icp is set up: it imports torch's
# flop counter, which imports Triton where installed (CUDA builds of torch), and Triton's LLVM
# crashes the process when Mesa's (the headless OpenGL of model depth, and of depth_range
# before it used surface points) is already loaded.
from evtrack.models.estimator import check_rgb
from evtrack.runtime.blas_threads import BlasThreads
from evtrack.runtime.jit import warm_up
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.depth_fusion import DepthFusion
from evtrack.tracking.depth_sources import DepthSource, ModelDepth, SensorDepth
from evtrack.tracking.event_gate import EventGate
from evtrack.tracking.inputs import (
    DepthFrame,
    FrameInput,
    FrameQueue,
    MeasurementQueue,
    PendingPoseCall,
    PoseMiss,
    StreamClock,
    TwistMeasurement,
)
from evtrack.tracking.load_control import LoadController
from evtrack.tracking.motion import MotionContext, MotionServices, motion_source_class
from evtrack.tracking.offline import PreparedDepth, push_sequence
from evtrack.tracking.outputs import TrackOutputs, ViewCheck, extrapolated, quat_to_matrix
from evtrack.tracking.pose_alignment import PoseRayAligner
from evtrack.tracking.pose_calls import PoseCaller
from evtrack.tracking.pose_flips import HalfTurnResolver
from evtrack.tracking.pose_gate import PoseGate
from evtrack.tracking.pose_sources import PoseMeasurement, PoseSource, checked_pose
from evtrack.tracking.pose_timeline import PoseTimeline, pose_measurement_value
from evtrack.tracking.roi_depth import RoiDepth
from evtrack.tracking.scheduler import StepScheduler
from evtrack.tracking.silhouette import Silhouette, SilhouettePolygon
from evtrack.tracking.stats import StageTimer, TrackerStats
from evtrack.tracking.trajectory import STATUS_LOST, STATUS_TRACKING, STATUS_WAITING, Trajectory
from evtrack.utils import threads_per_job

__all__ = ["Tracker", "TrackerStats"]


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


def _load_mesh(mesh: Any) -> tuple[Any, np.ndarray]:
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


def _needs_mesh(mesh: Any, what: str) -> None:
    if mesh is None:
        raise ConfigError(f"{what} needs the object's mesh (an ObjectMesh or a mesh file), not "
                          "bare vertices")


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
        stats: :class:`TrackerStats` of the run since the last :meth:`reset`.
        motion: the motion source of ``config.method``
            (:class:`~evtrack.tracking.motion.MotionSource`; e.g. ``motion.flow``, ``motion.vkf``
            for the event methods).
        ukf: the pose filter; timeline: its rolling past (:mod:`~evtrack.tracking.pose_timeline`).
        roi_depth, gate, load, pose_gate, pose_calls, depth_fusion, outputs, view: the parts
            (see the module docstring); ``depth_fusion`` is ``None`` without one.

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
        self.config = cfg = config if config is not None else TrackerConfig()
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
        aligned = self.rgb_camera == camera and bool(
            torch.allclose(self.T_event_rgb, torch.eye(4, dtype=torch.float64)))
        self.motion = motion_source_class(cfg.method)(MotionContext(
            cfg, camera, self.rgb_camera, self.T_event_rgb, self.device, vertices,
            self.silhouette, aligned))
        self.roi_depth = RoiDepth(self._make_depth_source(vertices), cfg.max_depth_age_ms)
        self.pose_gate = self._make_pose_gate(vertices)
        self.ukf = self.motion.pose_filter()
        self.timeline = PoseTimeline(self.ukf, int(round(cfg.history_ms * 1e3)))
        self.depth_fusion = self._make_depth_fusion()
        self._blas = BlasThreads(cfg.blas_threads)
        self.gate = EventGate(camera, self.silhouette, cfg.mask_margin_px, cfg.burst_rate_hz,
                              cfg.flow.roi_size)
        self.load = LoadController.from_config(cfg)
        self.view = ViewCheck(self.silhouette, cfg.min_visible_fraction, cfg.lost_after_ms,
                              cfg.velocity_step_us)
        self.pose_calls = PoseCaller(pose_source, cfg.pose_period_us, cfg.pose_min_confidence)
        self.scheduler = StepScheduler(self)
        self.motion.bind(MotionServices(
            now=lambda: self.stream.now, initialized=lambda: self.initialized, pose=self.pose,
            past_pose=self._past_pose, segment_pose=self._segment_pose,
            schedule=self._schedule_now, step_runs=lambda: self.step_runs,
            timeline=self.timeline, depth=self.roi_depth, gate=self.gate))
        self._async_poses = False  # inside track() with pose_async
        self.reset()

    def _make_depth_source(self, vertices: np.ndarray) -> DepthSource:
        """The depth of the sensing camera (the event camera's, the RGB camera's for a
        frame-based motion source): sensor frames or the mesh rendered at the pose."""
        cfg = self.config
        cam = self.motion.sensing_camera()
        if cfg.depth_source == "model":
            _needs_mesh(self.mesh, "depth_source 'model'")
            return ModelDepth(self.mesh, cam, cfg.model_depth_scale, cfg.model_depth_interval_us,
                              cfg.depth_patch_px, cfg.depth_stride_px)
        if self.motion.depth_from_event() is not None:  # the frames are the sensing camera's
            return SensorDepth(cam, cam, None, cfg.depth_patch_px, cfg.depth_stride_px)
        return SensorDepth(cam, self.rgb_camera, self.T_event_rgb, cfg.depth_patch_px,
                           cfg.depth_stride_px)

    def _make_pose_gate(self, vertices: np.ndarray) -> PoseGate:
        cfg = self.config
        source = self.roi_depth.source
        sensor = isinstance(source, SensorDepth)
        aligner = None
        if cfg.pose_depth_align and self.mesh is not None and sensor:
            aligner = PoseRayAligner.from_mesh(self.mesh, source.camera,
                                               max_shift_m=cfg.pose_depth_align_max_m)
        half_turns = None
        if cfg.pose_half_turn_axes:
            lo, hi = vertices.min(axis=0), vertices.max(axis=0)
            half_turns = HalfTurnResolver(cfg.pose_half_turn_axes, (lo + hi) / 2,
                                          cfg.pose_half_turn_max_view_deg)
        to_depth = self.motion.depth_from_event()
        return PoseGate(cfg, self.motion.sensing_silhouette(), sensor, aligner, half_turns,
                        None if to_depth is None else to_depth.numpy(),
                        None if to_depth is None else self.T_event_rgb.numpy())

    def _make_depth_fusion(self) -> DepthFusion | None:
        cfg = self.config
        if self.motion.poses_only_initialise or not (cfg.depth_range or cfg.depth_icp):
            return None
        if cfg.depth_range:
            _needs_mesh(self.mesh, "depth_range")
        if cfg.depth_icp:
            _needs_mesh(self.mesh, "depth_icp")
        # the depth maps are in the sensing camera, the filter's pose in the event camera
        to_depth = self.motion.depth_from_event()
        T = torch.eye(4, dtype=torch.float64) if to_depth is None else to_depth
        return DepthFusion(cfg, self.mesh, self.roi_depth.source.camera, T.numpy(),
                           self.timeline, self._past_pose)

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
        self.stats = TrackerStats()
        parts = (self.motion, self.roi_depth, self.gate, self.pose_gate, self.pose_calls,
                 self.depth_fusion)
        for part in parts:
            if part is not None:
                part.stats = self.stats
        self.motion.reset()
        self.ukf.reset(1)
        for part in (self.roi_depth, self.gate, self.load, self.pose_gate, self.pose_calls,
                     self.depth_fusion, self.scheduler):
            if part is not None:
                part.reset()
        self.view.out_of_view_us = 0
        self.stream = StreamClock(self.config.velocity_step_us)
        self.measurements = MeasurementQueue()
        self.frames = FrameQueue()
        self.outputs = TrackOutputs()
        self._ever_lost = False
        self._misses = 0  # pose-source misses in a row
        self._held: np.ndarray | None = None
        if t_us is not None:
            self._start_clock(int(t_us))
        if pose is not None:
            t, q = pose_measurement_value(pose, torch.float64, self.device)
            self.ukf.reset(1, t=t, q=q)
            self.timeline.start(self.stream.now)

    def _start_clock(self, t_us: int) -> None:
        self.timeline.start(self.stream.start(t_us))

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
        return self.stream.now

    def _present_pose(self) -> np.ndarray:
        return quat_to_matrix(self.ukf.t.tolist()[0], self.ukf.q.tolist()[0])

    def _segment_pose(self) -> tuple[np.ndarray, SilhouettePolygon | None]:
        """The pose and silhouette of a new segment of a step group: the pose filter's now;
        the motion source learns it (the velocity filter's pivot)."""
        pose = self._present_pose()
        poly = self.silhouette.polygon(pose) if np.isfinite(pose).all() else None
        self.motion.segment_started(pose)
        return pose, poly

    def _past_pose(self, t_us: int) -> np.ndarray | None:
        """(4, 4) the pose the filter had at a kept past time (:meth:`PoseTimeline.pose_at
        <evtrack.tracking.pose_timeline.PoseTimeline.pose_at>`), or ``None``."""
        tq = self.timeline.pose_at(t_us)
        return None if tq is None else quat_to_matrix(tq[0].tolist(), tq[1].tolist())

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
        self.stream.check_events(t_first, t_last)
        if self.stream.now is None:
            self._start_clock(t_first)
        self.stream.last_event_us = t_last
        self.stream.moved_by = f"push_events (events up to t={t_last} µs)"
        self.stats.events += len(events)
        self.scheduler.buffer.append(events.to("cpu"))
        self._advance_to(t_last)

    def advance(self, t_us: int) -> None:
        """Declare that every event before ``t_us`` was pushed: close the step groups (of
        ``flow_batch_steps`` steps) ending by then, and the frames before them."""
        t_us = int(t_us)
        if t_us > self.stream.horizon:
            self.stream.moved_by = f"advance(t_us={t_us})"
        self._advance_to(t_us)

    def _advance_to(self, t_us: int) -> None:
        """:meth:`advance` for the input calls (which name themselves as the clock's mover)."""
        t_us = int(t_us)
        if self.stream.now is None:
            self._start_clock(t_us)
        self.stream.horizon = max(self.stream.horizon, t_us)
        with self._blas:
            self.scheduler.advance(t_us, whole_groups=True)

    def flush(self) -> None:
        """Close every step ending by the latest time known (the last event pushed or the last
        :meth:`advance`), also inside an unfinished step group, and process the frames queued up
        to then. Call it at the end of a stream."""
        if self.stream.now is None:
            return
        with self._blas:
            self.scheduler.advance(self.stream.horizon, whole_groups=False)
            self._frames_due(self.stream.horizon + 1)
        self.measurements.replace_pending_calls(self._settled)

    def _settled(self, available: int, call: PendingPoseCall) -> tuple[int, Any]:
        """A worker's pose-source call not due yet, waited for and left pending as the
        synchronous path would have (the pose or the miss scheduled for its time): the end of
        a stream then leaves the same state and statistics either way."""
        m = self.pose_calls.result(call.result)
        if self.pose_calls.accepted(m):
            return max(m.t_us, available), m
        return available, PoseMiss(call.t_us)

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
                (sensor depth: the previous depth frame is kept).

        Raises:
            ValueError: an RGB or depth array of the wrong shape or type (nothing is queued).
                A frame given as a callable is read when it is processed, so its errors are
                raised then, from the call that processed it, naming the frame's time; the
                tracker stays usable (the steps of the step group it interrupted get no
                flow).
        """
        t_us = int(t_us)
        if depth is not None and not callable(depth) and self.roi_depth.sensor:
            self.roi_depth.source.check_frame(t_us, depth)
        self.stream.moved_by = f"push_frame(t_us={t_us})"
        if rgb is not None and not callable(rgb) and self._uses_rgb:
            _check_rgb(t_us, rgb, self.rgb_camera)
        if self.stream.now is None:
            self._start_clock(t_us)
        self.stats.frames += 1
        if depth is None:
            self.stats.frames_without_depth += 1
        self.frames.push(t_us, rgb, depth)
        with self._blas:
            if t_us < self.stream.now:
                self._frames_due(self.stream.now)
            self._advance_to(t_us)

    @property
    def _uses_rgb(self) -> bool:
        """Whether the RGB images are read: by the pose source or the motion source."""
        return self.pose_source is not None or self.motion.uses_rgb

    def _frames_due(self, t_before: int) -> None:
        """Process the queued frames taken before ``t_before``."""
        for t_us, rgb, depth in self.frames.pop_before(t_before):
            with StageTimer(self.stats.time_s, "frames"):
                try:
                    self._process_frame(t_us, rgb, depth)
                except Exception as exc:
                    if hasattr(exc, "add_note"):  # Python >= 3.11
                        exc.add_note(f"(while processing the frame pushed for t={t_us} µs; "
                                     "the tracker goes on without it)")
                    raise

    def _process_frame(self, t_us: int, rgb: FrameInput, depth: FrameInput) -> None:
        depth_map = self._take_depth(t_us, depth)
        if rgb is None:
            return
        get_rgb = ((lambda: _check_rgb(t_us, rgb(), self.rgb_camera)) if callable(rgb)
                   else (lambda: rgb))
        image = self.motion.on_rgb(t_us, get_rgb) if self.motion.uses_rgb else None
        if not self._wants_pose(t_us):
            return
        self.stats.pose_calls += 1
        available = t_us + self.config.pose_latency_us
        uses_depth = self.pose_calls.uses_depth
        if depth_map is None and depth is not None and uses_depth:
            depth_map = depth() if callable(depth) else depth
        depth_in = depth_map if uses_depth else None
        prior = self._pose_prior(t_us)
        if self._async_poses and available > self.stream.now:
            # computed in the worker (the RGB frame read there too), taken at `available`:
            # the same result at the same moment for the filter
            future = self.pose_calls.submit(t_us, image if image is not None else get_rgb,
                                            depth_in, prior)
            self.measurements.push(available, PendingPoseCall(t_us, future))
            return
        m = self.pose_calls.call(t_us, image if image is not None else get_rgb(), depth_in,
                                 prior)
        if self.pose_calls.accepted(m):
            self.push_pose(m, available_us=available)
        else:
            self.stats.pose_misses += 1
            self._schedule_now(max(available, self.stream.now), PoseMiss(t_us))

    def _take_depth(self, t_us: int, depth: FrameInput) -> np.ndarray | None:
        """A sensor depth frame: in use for the RoIs (unless a newer one is), kept for the
        pose gate and measured by the depth fusions; returns it as read (``None``: none)."""
        if depth is None or not self.roi_depth.sensor:
            return None
        source = self.roi_depth.source
        depth_map = depth() if callable(depth) else depth
        if isinstance(depth_map, PreparedDepth):  # from track(): prepared ahead
            event_map, depth_map = depth_map.event_map, depth_map.raw
        else:
            event_map = source.prepare(t_us, depth_map)
        if source.t_us is None or t_us >= source.t_us:
            source.set_prepared(t_us, event_map)  # else the newer map stays in use
        self.pose_gate.remember_depth(t_us, event_map)
        if self.depth_fusion is not None:
            self._schedule_now(t_us, DepthFrame(t_us, event_map))
        return depth_map

    def _wants_pose(self, t_us: int) -> bool:
        if self.pose_source is None:
            return False
        if self.motion.poses_only_initialise and self.initialized:
            return False
        return self.pose_calls.wants(t_us)

    def _pose_prior(self, t_us: int) -> np.ndarray | None:
        """(4, 4) the pose (event camera frame) handed to the pose source for the frame at
        ``t_us`` (``TrackerConfig.pose_prior``), or ``None``: no prior wanted, a source that
        takes none, or no track (before the first pose, after a loss)."""
        if not (self.config.pose_prior and self.initialized and self.pose_calls.accepts_prior):
            return None
        return np.array(self.pose(t_us), dtype=np.float64)

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
        if self.stream.now is None:
            self._start_clock(measurement.t_us)
            self.stream.moved_by = f"push_pose(t_us={measurement.t_us})"
        now = self.stream.now
        avail = max(measurement.t_us, now if available_us is None else int(available_us))
        self.stats.poses += 1
        self.measurements.push(avail, measurement)
        with self._blas:
            self._apply_due(self.stream.now)

    # ------------------------------------------------------------------ measurements
    def _schedule_now(self, available_us: int, item: Any) -> None:
        """Queue a measurement and apply what is due at the clock."""
        self.measurements.push(available_us, item)
        self._apply_due(self.stream.now)

    def _apply_due(self, t_now: int) -> None:
        while (due := self.measurements.pop_due(t_now)) is not None:
            available, item = due
            self._apply(item, available, t_now)

    @singledispatchmethod
    def _apply(self, item: Any, available: int, t_now: int) -> None:
        raise TypeError(f"no handler for a queued {type(item).__name__}")

    @_apply.register
    def _(self, item: PoseMeasurement, available: int, t_now: int) -> None:
        self._fuse_pose(item)

    @_apply.register
    def _(self, item: DepthFrame, available: int, t_now: int) -> None:
        if self.initialized:
            self.depth_fusion.fuse_range(item)
        if self.initialized:
            self.depth_fusion.fuse_alignment(item)

    @_apply.register
    def _(self, item: PoseMiss, available: int, t_now: int) -> None:
        self._on_miss(t_now)

    @_apply.register
    def _(self, item: TwistMeasurement, available: int, t_now: int) -> None:
        if self.initialized and self.timeline.add(item.t_us, "twist", (item.twist,), item.cov):
            self.stats.twist_measurements += 1

    @_apply.register
    def _(self, item: PendingPoseCall, available: int, t_now: int) -> None:
        """A worker's pose-source result, due at ``available`` (<= ``t_now``): handled as the
        synchronous path's pose or miss, scheduled for ``available`` at the frame's turn,
        would be now."""
        m = self.pose_calls.result(item.result)  # a pose source's exception is raised here
        if not self.pose_calls.accepted(m):
            self._on_miss(t_now)
            return
        due = max(m.t_us, available)
        if due <= t_now:
            self._fuse_pose(m)
        else:  # a measurement time after the frame's (not from the built-in sources)
            self.measurements.push(due, m)

    def _on_miss(self, t_now: int) -> None:
        self._misses += 1
        limit = self.config.lost_after_misses
        if limit and self._misses >= limit and self.initialized:
            self._lose(t_now)

    def _fuse_pose(self, m: PoseMeasurement) -> None:
        checked = self.pose_gate.checked(m)
        if checked is None:
            return
        m = checked
        self._misses = 0
        was_init = self.initialized
        if self.motion.poses_only_initialise and was_init:
            return  # poses only (re-)initialise
        turned_back = False  # the track deemed half a turn off: re-initialise on m
        if self.pose_gate.half_turns is not None and was_init:
            m, turned_back = self.pose_gate.nearer_half_turn(m, self._past_pose(m.t_us))
        ukf = self.ukf
        rejected, reinit = int(ukf.rejected[0]), int(ukf.reinitialised[0])
        t, q = pose_measurement_value(m.pose, ukf.t.dtype, self.device)
        cov = None if m.cov is None else m.cov.to(ukf.t.dtype).to(self.device).unsqueeze(0)
        if m.t_us > self.timeline.now:  # pragma: no cover - _apply_due never lets it happen
            raise RuntimeError(f"pose at {m.t_us} µs applied before the clock reached it")
        agrees = was_init and self.pose_gate.agrees_with_rejected(m.t_us, m.pose)
        kind = "pose_reinit" if turned_back or agrees else "pose"
        if not self.timeline.add(m.t_us, kind, (t, q), cov):
            self.stats.poses_late += 1
            return
        newly_rejected = int(ukf.rejected[0]) - rejected
        newly_reinit = int(ukf.reinitialised[0]) - reinit
        self.stats.poses_rejected += max(0, newly_rejected)
        self.stats.reinitialisations += max(0, newly_reinit)
        self.pose_gate.fused(m, rejected=newly_rejected > 0 and newly_reinit <= 0)
        if self.initialized and not was_init:
            self.view.out_of_view_us = 0
            self.motion.track_started(m.t_us)

    def _budgets_after_group(self, wall_s: float, stream_s: float) -> None:
        """``realtime_load``: the load controller's budgets after a step group."""
        load = self.load
        load.adapt(wall_s, stream_s)
        st = self.stats
        st.search_budget_min = load.search_budget_min
        st.event_budget_min = load.event_budget_min
        st.groups_over_load = load.groups_over_load

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
        if self.view.in_view(t, q):
            return False
        self._lose(t1, quat_to_matrix(t, q))
        return True

    def _lose(self, t_now: int, held: np.ndarray | None = None) -> None:
        """The object is lost: hold the last pose (``held``, default the pose filter's),
        forget the filters' states."""
        self._held = self._present_pose() if held is None else held
        self._ever_lost = True
        self.stats.lost += 1
        self.view.out_of_view_us = 0
        self.pose_gate.forget_track()
        self.ukf.reset(1)
        self.motion.lost()
        self.timeline.start(t_now)

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
        twist = self.motion.twist() if status == STATUS_TRACKING else np.zeros(6)
        self.outputs.append(t1, tq.astype(np.float64), twist, status)

    def trajectory(self) -> Trajectory:
        """Every output so far: one sample at the end of each velocity step."""
        meta = {"config": self.config.to_dict(), "stats": self.stats.to_dict()}
        return self.outputs.trajectory(self.method, meta)

    def pose(self, t_us: int | None = None) -> np.ndarray:
        """The pose (4, 4) at ``t_us`` (default: now).

        For a past time, the output of the last step ending at or before it, moved on by that
        step's twist; for a time after the clock, the current pose predicted with the current
        twist. NaN before the first pose.
        """
        return extrapolated(*self._lookup(t_us), t_us)

    def twist(self, t_us: int | None = None) -> np.ndarray:
        """The twist (6,) ``[v_o, ω]`` at ``t_us`` (default: now); see :meth:`pose`."""
        return self._lookup(t_us)[0]

    def _lookup(self, t_us: int | None) -> tuple[np.ndarray, np.ndarray, int]:
        now = self.stream.now
        if now is None:
            return np.zeros(6), np.full((4, 4), np.nan), 0
        if t_us is None or t_us >= now or not len(self.outputs):
            if self.status == STATUS_TRACKING:
                return self.motion.twist(), self._present_pose(), now
            held = self._held if self._held is not None else np.full((4, 4), np.nan)
            return np.zeros(6), held, now
        return self.outputs.sample_before(t_us)

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
                self.reset()
                prepare = self.roi_depth.source.prepare if self.roi_depth.sensor else None
                push_sequence(self, sequence, prepare, progress)
                return self.trajectory()
        finally:
            self._async_poses = False
            torch.set_num_threads(threads)
