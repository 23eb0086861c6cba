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
depth fusions (:mod:`~evtrack.tracking.depth_fusion`), the appearance alignment
(:mod:`~evtrack.tracking.appearance_fusion`) and the outputs (:mod:`~evtrack.tracking.outputs`).

With ``TrackerConfig.pose_source: model`` the object's mesh is the pose source: from a start
pose (:meth:`Tracker.reset`, :meth:`Tracker.start_from_frame`), the depth and appearance
alignments correct the event track; no network is called.

The methods (``TrackerConfig.method``, one motion source each):

* ``full``: as above (the paper). Optionally the pose filter learns a bias of the twist's
  velocity that grows with the object's speed from the pose innovations
  (``pose_ukf.velocity_bias``, off by default; the twists the tracker outputs are the velocity
  filter's, without it).
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

import math
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evtrack.camera import PinholeCamera
from evtrack.configs import checked_device
from evtrack.errors import ConfigError, EventsError
from evtrack.events import Events
from evtrack.geometry import matrix_to_tq
from evtrack.runtime.blas_threads import BlasThreads
from evtrack.runtime.jit import warm_up
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.event_gate import EventGate
from evtrack.tracking.frames import FrameIntake, checked_rgb
from evtrack.tracking.fusion import MeasurementFusion
from evtrack.tracking.inputs import (
    FrameInput,
    MeasurementQueue,
    StreamClock,
)
from evtrack.tracking.load_control import LoadController
from evtrack.tracking.motion import MotionContext, MotionServices, motion_source_class
from evtrack.tracking.observability import RotationObservability, UnobservedRotation
from evtrack.tracking.occlusion import Occluders
from evtrack.tracking.offline import push_sequence
from evtrack.tracking.outputs import TrackOutputs, ViewCheck, extrapolated, quat_to_matrix
from evtrack.tracking.pose_calls import PoseCaller
from evtrack.tracking.pose_sources import PoseMeasurement, PoseSource, checked_pose
from evtrack.tracking.pose_timeline import PoseTimeline, pose_measurement_value
from evtrack.tracking.roi_depth import RoiDepth
from evtrack.tracking.scheduler import StepScheduler
from evtrack.tracking.silhouette import Silhouette, SilhouettePolygon
from evtrack.tracking.stats import TrackerStats
from evtrack.tracking.trajectory import STATUS_LOST, STATUS_TRACKING, STATUS_WAITING, Trajectory
from evtrack.tracking.wiring import (
    load_mesh,
    make_appearance_fusion,
    make_denoiser,
    make_depth_fusion,
    make_depth_source,
    make_pose_gate,
)
from evtrack.utils import threads_per_job

__all__ = ["Tracker", "TrackerStats"]


def _check_pose_source(config: TrackerConfig, source: PoseSource | None) -> None:
    """Refuse a pose source where ``config.pose_source`` is ``"model"``.

    Raises:
        ConfigError: saying what to do instead.
    """
    if source is not None and config.pose_source == "model":
        raise ConfigError("TrackerConfig.pose_source is 'model' (poses from the mesh alone), "
                          f"but a pose source ({type(source).__name__}) was given: pass none, "
                          "or set pose_source: network and appearance.enabled: true to use "
                          "both")


class Tracker:
    """Track one known rigid object with an event camera and an RGB-D camera.

    Args:
        config: :class:`~evtrack.tracking.config.TrackerConfig` (default: its defaults).
        camera: the event camera.
        mesh: the object: an :class:`~evtrack.sim.objects.ObjectMesh`, a mesh file (read in its
            own frame, which must be the poses' object frame), or (V, 3) vertices (enough for
            everything but ``depth.source: model``).
        pose_source: gives absolute poses from RGB frames (:mod:`evtrack.tracking.pose_sources`);
            ``None``: poses only through :meth:`push_pose` or :meth:`reset`. None with
            ``config.pose_source: model`` (the mesh is the pose source there).
        rgb_camera: the RGB-D camera (default: the event camera).
        T_event_rgb: (4, 4) maps RGB-camera points into the event camera (default identity).

    Attributes:
        clock: ``() -> seconds``, the wall clock ``TrackerConfig.load.realtime`` measures the
            processing with (default :func:`time.perf_counter`; replaceable, e.g. in tests).
        stats: :class:`TrackerStats` of the run since the last :meth:`reset`.
        motion: the motion source of ``config.method``
            (:class:`~evtrack.tracking.motion.MotionSource`; e.g. ``motion.flow``, ``motion.vkf``
            for the event methods).
        ukf: the pose filter; timeline: its rolling past (:mod:`~evtrack.tracking.pose_timeline`).
        roi_depth, gate, load, pose_gate, pose_calls, depth_fusion, appearance, outputs, view: the
            parts (see the module docstring); ``depth_fusion`` and ``appearance`` are ``None``
            without one.
        scheduler, frames, fusion: the internal drivers (:mod:`~evtrack.tracking.scheduler`,
            :mod:`~evtrack.tracking.frames`, :mod:`~evtrack.tracking.fusion`) that run the
            steps, take the frames and apply the queued measurements.

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
        self.clock: Callable[[], float] = time.perf_counter
        self.mesh, vertices = load_mesh(mesh)
        self.device = checked_device(cfg.device, "tracker config field 'device'")
        self.silhouette = Silhouette(vertices, camera)
        self.method = cfg.method
        aligned = self.rgb_camera == camera and bool(
            torch.allclose(self.T_event_rgb, torch.eye(4, dtype=torch.float64)))
        self.motion = motion_source_class(cfg.method)(MotionContext(
            cfg, camera, self.rgb_camera, self.T_event_rgb, self.device, vertices,
            self.silhouette, aligned))
        depth = make_depth_source(cfg, self.motion, self.mesh, self.rgb_camera,
                                  self.T_event_rgb)
        self.roi_depth = RoiDepth(depth, cfg.depth.max_age_ms, cfg.depth.range_sigmas)
        self.pose_gate = make_pose_gate(cfg, self.motion, self.mesh, vertices, depth,
                                        self.T_event_rgb)
        self.ukf = self.motion.pose_filter()
        self.timeline = PoseTimeline(self.ukf, int(round(cfg.history_ms * 1e3)))
        self.depth_fusion = make_depth_fusion(cfg, self.motion, self.mesh, depth, self.timeline,
                                              self._past_pose)
        self.appearance = make_appearance_fusion(cfg, self.motion, self.mesh, self.rgb_camera,
                                                 self.T_event_rgb, self.timeline, self._past_pose)
        self.occluders = Occluders()
        """Nearer tracked objects whose pixels the frame alignments leave out; set by
        :class:`~evtrack.tracking.multi.MultiTracker` per window, none otherwise."""
        for fusion in (self.depth_fusion, self.appearance):
            if fusion is not None:
                fusion.occluders = lambda: self.occluders
        self._blas = BlasThreads(cfg.blas_threads)
        self.gate = EventGate(camera, self.silhouette, cfg.mask_margin_px, cfg.burst_rate_hz,
                              cfg.flow.roi_size, make_denoiser(cfg, self.motion, camera),
                              burst_baseline_us=int(round(cfg.burst_baseline_ms * 1e3)),
                              burst_factor=cfg.burst_factor)
        self.load = LoadController.from_config(cfg)
        self.view = ViewCheck(self.silhouette, cfg.min_visible_fraction, cfg.lost_after_ms,
                              cfg.velocity_step_us)
        _check_pose_source(cfg, pose_source)
        self.pose_calls = PoseCaller(pose_source, cfg.pose_period_us, cfg.pose_gate.min_confidence)
        self.scheduler = StepScheduler(self)
        self.fusion = MeasurementFusion(self)
        self.frames = FrameIntake(self)
        self.motion.bind(MotionServices(
            now=lambda: self.stream.now, initialized=lambda: self.initialized, pose=self.pose,
            past_pose=self._past_pose, segment_pose=self._segment_pose,
            schedule=self.fusion.schedule, step_runs=lambda: self.step_runs,
            timeline=self.timeline, depth=self.roi_depth, gate=self.gate))
        self.reset()

    @property
    def pose_source(self) -> PoseSource | None:
        """The pose source (replaceable: the next frames' calls go to the new one)."""
        return self.pose_calls.source

    @pose_source.setter
    def pose_source(self, source: PoseSource | None) -> None:
        _check_pose_source(self.config, source)
        self.pose_calls.source = source

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
            ValueError: a pose without ``t_us``, not a rigid (4, 4) transform, or with the
                object's origin behind the camera (checked before anything is reset).
        """
        if pose is not None and t_us is None:
            raise ValueError("reset: a starting pose needs its time t_us")
        if pose is not None:  # checked before anything is reset
            pose = checked_pose(pose, f"reset: starting pose at t={int(t_us)} µs")
            if not float(pose[2, 3]) > 0:
                raise ValueError(f"reset: the starting pose at t={int(t_us)} µs puts the "
                                 f"object's origin behind the event camera (z = "
                                 f"{float(pose[2, 3]):.3f} m); poses are object-to-camera "
                                 "(did you pass camera-to-object?)")
        self.stats = TrackerStats()
        parts = (self.motion, self.roi_depth, self.gate, self.pose_gate, self.pose_calls,
                 self.depth_fusion, self.appearance)
        for part in parts:
            if part is not None:
                part.stats = self.stats
        self.observability = RotationObservability()
        for fusion in (self.depth_fusion, self.appearance):
            if fusion is not None:
                fusion.observability = self.observability
        self.motion.reset()
        self.ukf.reset(1)
        for part in (self.roi_depth, self.gate, self.load, self.pose_gate, self.pose_calls,
                     self.depth_fusion, self.appearance, self.scheduler, self.fusion, self.frames):
            if part is not None:
                part.reset()
        self.view.out_of_view_us = 0
        self.stream = StreamClock(self.config.velocity_step_us)
        self.measurements = MeasurementQueue()
        self.outputs = TrackOutputs()
        self._ever_lost = False
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
        self._pose_depth_uncertainty()
        return pose, poly

    def _pose_depth_uncertainty(self) -> None:
        """Tell the RoI depth the pose filter's standard deviation (m) of the object origin's
        camera ``z`` now (``depth.range_sigmas``)."""
        if self.roi_depth.range_sigmas:
            self.roi_depth.set_pose_uncertainty(math.sqrt(max(float(self.ukf.cov[0, 2, 2]), 0.0)))

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

        With ``TrackerConfig.denoise`` on, the packet's sensor noise is removed here
        (:meth:`EventGate.denoised <evtrack.tracking.event_gate.EventGate.denoised>`).
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
        events = self.gate.denoised(events.to("cpu"))
        if len(events):
            self.scheduler.buffer.append(events)
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
            self.frames.due(self.stream.horizon + 1)
        self.measurements.replace_pending_calls(self.fusion.settled)

    def start_from_frame(self, t_us: int, rgb: np.ndarray, depth: np.ndarray,
                         box: tuple[int, int, int, int] | None = None, config: Any = None
                         ) -> Any:
        """Find the object's pose on the RGB-D frame taken at ``t_us`` from its textured mesh
        alone (:meth:`register_frame`) and start the track there (:meth:`reset`); the events
        and frames from ``t_us`` on follow.

        Returns:
            the :class:`~evtrack.models.mesh_registration.Registration` (pose in the RGB
            camera, how sure it is, the box).

        Raises:
            ConfigError: a tracker without the object's textured mesh.
            ValueError: what :meth:`register_frame` refuses.
        """
        found = self.register_frame(t_us, rgb, depth, box, config)
        self.reset(self.T_event_rgb.numpy() @ found.pose, int(t_us))
        return found

    def register_frame(self, t_us: int, rgb: np.ndarray, depth: np.ndarray,
                       box: tuple[int, int, int, int] | None = None, config: Any = None
                       ) -> Any:
        """Find the object's pose on one RGB-D frame from its textured mesh alone, without
        touching the track. With ``box``, around the object in the RGB image, see
        :func:`evtrack.models.mesh_registration.register_mesh`; without, the object is looked
        for where the depth stands out of the scene's planes with the object's size
        (:func:`evtrack.models.mesh_registration.find_mesh`). ``config``: the
        :class:`~evtrack.models.mesh_registration.RegistrationConfig`.

        Args:
            t_us: the frame's time (µs).
            rgb: (H, W, 3) uint8 image of the RGB-D camera.
            depth: (H, W) metres registered to it (NaN or <= 0: missing).
            box: ``(u0, v0, u1, v1)`` pixels of the RGB image around the object, or ``None``.

        Returns:
            the :class:`~evtrack.models.mesh_registration.Registration`; its ``pose`` is in
            the RGB camera (``T_event_rgb @ pose`` in the event camera).

        Raises:
            ConfigError: a tracker without the object's textured mesh.
            ValueError: what :func:`~evtrack.models.mesh_registration.register_mesh` or
                :func:`~evtrack.models.mesh_registration.find_mesh` refuses.
        """
        from evtrack.models.mesh_registration import find_mesh, register_mesh

        if self.mesh is None:
            raise ConfigError("start_from_frame needs the object's textured mesh (an ObjectMesh "
                              "or a mesh file), not bare vertices")
        rgb = checked_rgb(int(t_us), rgb, self.rgb_camera)
        depth = np.asarray(depth, np.float32)
        if box is None:
            return find_mesh(self.mesh, self.rgb_camera, rgb, depth, config)
        return register_mesh(self.mesh, self.rgb_camera, rgb, depth, box, config)

    def push_frame(self, t_us: int, rgb: FrameInput = None, depth: FrameInput = None) -> None:
        """Add the RGB-D frame taken at ``t_us`` (after the events before ``t_us``).

        The frame is processed once the clock reaches it (after the steps ending by ``t_us``);
        a frame older than the clock is processed at once. A depth frame older than the depth
        map in use does not replace it (the RoIs keep the newer one); it still serves the
        pose checks of its own time and the depth fusions (``depth_fusion.range``,
        ``depth_fusion.icp``).

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
            checked_rgb(t_us, rgb, self.rgb_camera)
        if self.stream.now is None:
            self._start_clock(t_us)
        self.stats.frames += 1
        if depth is None:
            self.stats.frames_without_depth += 1
        self.frames.push(t_us, rgb, depth)
        with self._blas:
            if t_us < self.stream.now:
                self.frames.due(self.stream.now)
            self._advance_to(t_us)

    @property
    def _uses_rgb(self) -> bool:
        """Whether the RGB images are read: by the pose source, the motion source or the
        appearance alignment."""
        return (self.pose_source is not None or self.motion.uses_rgb
                or self.appearance is not None)

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
            self.fusion.apply_due(self.stream.now)

    def _budgets_after_group(self, wall_s: float, stream_s: float) -> None:
        """``load.realtime``: the load controller's budgets after a step group."""
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
        meta = {"config": self.config.to_dict(), "stats": self.stats.to_dict(),
                "rotations": self.observability.to_dict()}
        return self.outputs.trajectory(self.method, meta)

    def unobserved_rotations(self, max_std_deg: float = 2.0) -> list[UnobservedRotation]:
        """The object axes about which no frame alignment fused since the last :meth:`reset`
        (``depth_fusion.icp``, ``appearance``, ``pose_source: model``) observed the rotation
        (:mod:`~evtrack.tracking.observability`): those about which one alignment's standard
        deviation was ``max_std_deg`` or more for every source, e.g. a plain cylinder's spin
        about its axis with depth alone. Empty without such alignments; rotations about these
        axes were carried by the events and the pose source only."""
        return self.observability.unobserved(max_std_deg)

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
    def track(self, sequence, progress: bool = False,
              start_pose: Tensor | np.ndarray | None = None,
              start_t_us: int | None = None) -> Trajectory:
        """Track a whole :class:`~evtrack.Sequence` (events and frames in time order).

        The pose source runs on the frames at ``pose_rate_hz`` and its poses reach the filter
        ``pose_latency_ms`` later, as they would live. With ``start_pose`` (4, 4) the track
        starts from it at ``start_t_us`` (as :meth:`reset` does), e.g. the ``velocity`` method
        on a recording without a pose source, or ``pose_source: model``; the events and frames
        before ``start_t_us`` are then left out (the stream starts with the track).

        Returns:
            the :class:`~evtrack.tracking.trajectory.Trajectory` (one sample per velocity step).
        """
        threads = torch.get_num_threads()
        if self.config.torch_threads > 0:
            torch.set_num_threads(threads_per_job(self.config.torch_threads))
        self.pose_calls.in_worker = self.config.pose_async
        try:
            with self._blas:  # the worker's pose calls all end inside (flush settles them)
                self.reset(start_pose, start_t_us)
                prepare = self.roi_depth.source.prepare if self.roi_depth.sensor else None
                push_sequence(self, sequence, prepare, progress,
                              None if start_pose is None else start_t_us)
                return self.trajectory()
        finally:
            self.pose_calls.in_worker = False
            torch.set_num_threads(threads)
