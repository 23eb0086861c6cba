"""``MultiTracker``: several objects tracked from one event stream and one set of RGB-D frames.

Each object has its own :class:`~evtrack.tracking.tracker.Tracker` (its mesh, pose source and
filters). The multi-object tracker sits in front of them and shares the stream out:

* **Windows.** Time is cut into assignment windows of one step group each
  (``velocity_step_us * flow_batch_steps``, 40 ms by default), starting at the first input.
  When the stream reaches a window, every object's tracker is advanced to the window's start,
  and its silhouette is predicted over the window: the convex hull of the silhouette at its
  pose now and the one its twist predicts at the window's end (as the tracker's own event gate
  sweeps it), grown by ``mask_margin_px``.
* **Assignment** (:func:`~evtrack.tracking.assignment.assign_events`): an event inside one
  object's swept silhouette is that object's; inside several, the nearest one's (smallest
  camera ``z`` of its origin: it occludes the others there); inside none, nobody's.
* **Dispatch.** Each tracker receives its own events and those of nobody (its event gate drops
  the latter as it would alone, and its burst detection still sees the background); the
  events owned by another object never reach it. The counts are in :attr:`stats`.
* **Frames** go to every tracker (each calls its own pose source on them); a frame is read
  once and shared.
* **Occlusion in the frames.** Each tracker is told the objects nearer than its own at the
  window's start, with their predicted motion (:attr:`Tracker.occluders
  <evtrack.tracking.tracker.Tracker.occluders>`): its depth and appearance alignments
  (``pose_source: model``, ``depth_fusion.icp``, ``appearance``) leave out the pixels those
  objects' convex silhouettes cover.

* **First poses.** Before an object's first pose nobody owns an event. The first of the
  trackers waiting for their first pose (the keeper) runs the flow on the events nobody owns
  (``remeasure.before_pose``) and keeps the unposed steps; the others run no flow and share
  its kept steps (with the same config; :meth:`_share_unposed`). Each object's late first
  pose measures the kept steps again inside its silhouette (``remeasure.on_pose``); when the
  keeper's object is tracked, the next waiting tracker goes on keeping them. The check that
  the pose explains the kept events (``remeasure.min_inside``) is off here: the kept flows
  are every waiting object's, which no one pose explains. With the check, the oracle's
  four-object ``apart`` set tracked at 5.72 cm / 9.67° (the check refused every object's
  first pose, leaving the motion of all objects' events to carry it); without, 4.64 cm /
  9.02°; sharing the keeper's flow instead of one flow per waiting tracker: 4.60 cm / 8.97°,
  and the four trackers took 4.73 s instead of 4.87 s (6.11 s -> 5.29 s on the
  ``crossing`` set, whose objects wait with more events).

The windows are fixed by the clock, and each window's silhouettes are computed from trackers
that have seen exactly the stream before the window's start, so the trajectories do not depend
on how the stream was cut into packets: streaming equals offline.

Cost: the event flow and the filters run per object on its own events (before the first
poses, one flow for all waiting objects); the assignment is a few polygons per window and one
pixel test per event and object.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError, EventsError
from evtrack.events import Events
from evtrack.tracking.assignment import NO_OBJECT, ObjectMask, event_claims, owners
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.event_gate import moved_pose
from evtrack.tracking.occlusion import Occluder, Occluders
from evtrack.tracking.pose_sources import PoseSource
from evtrack.tracking.tracker import Tracker
from evtrack.tracking.trajectory import Trajectory

__all__ = ["MultiTracker", "TrackedObject", "AssignmentStats"]


@dataclass
class TrackedObject:
    """One object of a :class:`MultiTracker`.

    Attributes:
        name: unique name (the key of :meth:`MultiTracker.pose` and of the trajectories).
        mesh: its mesh: a file (glTF/OBJ/PLY, metres), an :class:`~evtrack.sim.ObjectMesh` or
            (V, 3) vertices.
        pose_source: its pose source (e.g. its network's), or ``None`` with
            ``pose_source: model`` or a start pose.
        start_pose: (4, 4) object-to-camera pose at the start time given to
            :meth:`MultiTracker.reset` / :meth:`MultiTracker.track`, or ``None`` (wait for
            the pose source).
        config: this object's tracker config; ``None``: the multi-tracker's.
    """

    name: str
    mesh: Any
    pose_source: PoseSource | None = None
    start_pose: np.ndarray | None = None
    config: TrackerConfig | None = None


@dataclass
class AssignmentStats:
    """Counts of the event assignment.

    Attributes:
        events: events pushed.
        per_object: events owned by each object (by name).
        unassigned: events in no object's silhouette (given to every tracker, which drops
            them unless they are in its own mask).
        contested: events in several silhouettes, given to the nearest object.
        windows: assignment windows opened.
    """

    events: int = 0
    per_object: dict[str, int] = field(default_factory=dict)
    unassigned: int = 0
    contested: int = 0
    windows: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"events": self.events, "per_object": dict(self.per_object),
                "unassigned": self.unassigned, "contested": self.contested,
                "windows": self.windows}


class MultiTracker:
    """Track several objects from one event stream (see the module docstring).

    Args:
        objects: the objects (at least one; unique names).
        config: the tracker config of every object without its own.
        camera: the event camera.
        rgb_camera, T_event_rgb: the RGB-D camera and its extrinsic (as :class:`Tracker`).

    Example:
        >>> cfg = TrackerConfig(pose_source="model")
        >>> multi = MultiTracker.for_sequence(seq, cfg)                    # doctest: +SKIP
        >>> tracks = multi.track(seq, start_poses=poses, start_t_us=0)    # doctest: +SKIP
        >>> tracks["005_tomato_soup_can"].save("can.csv")                 # doctest: +SKIP
    """

    def __init__(self, objects: Sequence[TrackedObject], config: TrackerConfig | None = None, *,
                 camera: PinholeCamera, rgb_camera: PinholeCamera | None = None,
                 T_event_rgb: Any = None) -> None:
        if not objects:
            raise ConfigError("MultiTracker: give at least one object")
        names = [o.name for o in objects]
        if len(set(names)) != len(names) or not all(names):
            raise ConfigError(f"MultiTracker: object names must be unique and non-empty, got "
                              f"{names}")
        self.objects = list(objects)
        self.config = config if config is not None else TrackerConfig()
        self.camera = camera
        self.trackers: dict[str, Tracker] = {
            o.name: Tracker(o.config or self.config, camera=camera, mesh=o.mesh,
                            pose_source=o.pose_source, rgb_camera=rgb_camera,
                            T_event_rgb=T_event_rgb)
            for o in self.objects}
        for tracker in self.trackers.values():  # see the module docstring, "First poses"
            remeasurer = getattr(tracker.motion, "remeasurer", None)
            if remeasurer is not None:
                remeasurer.check_events = False
        first = next(iter(self.trackers.values()))
        self._shares_unposed = len(self.trackers) > 1 and all(
            getattr(t.motion, "remeasurer", None) is not None and t.config == first.config
            for t in self.trackers.values())
        """Whether the waiting trackers share one keeper's unposed steps: every tracker keeps
        them (``remeasure.before_pose`` and ``on_pose``) with the same config."""
        windows = {t.config.velocity_step_us * t.config.flow_batch_steps
                   for t in self.trackers.values()}
        if len(windows) != 1:
            raise ConfigError("MultiTracker: every object's config must have the same "
                              "velocity_step_us * flow_batch_steps (the assignment window), "
                              f"got {sorted(windows)} µs")
        self.window_us = windows.pop()
        self.stats = AssignmentStats()
        self._reset_stream()

    @classmethod
    def for_sequence(cls, sequence, config: TrackerConfig | None = None,
                     pose_sources: Mapping[str, PoseSource] | None = None) -> MultiTracker:
        """A multi-tracker of every object of a :class:`~evtrack.Sequence`
        (:attr:`~evtrack.Sequence.objects`) with its cameras and extrinsic; ``pose_sources``
        by object name (objects without one get none)."""
        pose_sources = dict(pose_sources or {})
        objects = []
        for k, obj in enumerate(sequence.objects):
            mesh = sequence.object_mesh_file(k)
            if mesh is None:
                raise ConfigError(f"{sequence.root or sequence.meta.name}: object {obj.name!r} "
                                  "has no mesh (meta.yaml objects[].mesh)")
            objects.append(TrackedObject(obj.name, mesh, pose_sources.pop(obj.name, None)))
        if pose_sources:
            raise ConfigError(f"pose sources for objects the sequence does not have: "
                              f"{sorted(pose_sources)} (it has {[o.name for o in objects]})")
        return cls(objects, config, camera=sequence.meta.event_camera,
                   rgb_camera=sequence.meta.rgb_camera, T_event_rgb=sequence.meta.T_event_rgb)

    # ------------------------------------------------------------------ state
    def _reset_stream(self) -> None:
        self._origin: int | None = None      # the windows' grid starts here (µs)
        self._window: int | None = None      # index of the open window
        self._masks: list[ObjectMask] = []
        self._last_event_us: int | None = None
        self._horizon: int | None = None     # the latest time declared by advance()
        self._kept: dict | None = None       # the unposed steps the waiting trackers share
        for tracker in self.trackers.values():
            tracker.occluders = Occluders()

    def reset(self, t_us: int | None = None,
              start_poses: Mapping[str, np.ndarray] | None = None) -> None:
        """Start over. Objects with a start pose (``start_poses`` by name, else their
        :attr:`TrackedObject.start_pose`) start from it at ``t_us`` (required then); the
        others wait for their pose source."""
        start_poses = dict(start_poses or {})
        unknown = sorted(set(start_poses) - set(self.trackers))
        if unknown:
            raise ConfigError(f"start poses for unknown objects {unknown} (objects: "
                              f"{list(self.trackers)})")
        for obj in self.objects:
            pose = start_poses.get(obj.name, obj.start_pose)
            if pose is not None and t_us is None:
                raise ConfigError(f"object {obj.name!r} has a start pose: give its time t_us")
            self.trackers[obj.name].reset(pose, t_us if pose is not None else None)
        self.stats = AssignmentStats(per_object={o.name: 0 for o in self.objects})
        self._reset_stream()
        if t_us is not None and any(t.now_us is not None for t in self.trackers.values()):
            self._start(int(t_us))

    def start_from_frame(self, t_us: int, rgb: np.ndarray, depth: np.ndarray,
                         config: Any = None) -> dict[str, Any]:
        """Find every object's pose on the RGB-D frame taken at ``t_us`` from its textured
        mesh alone, each where the depth stands out of the scene's planes with its size
        (:meth:`Tracker.register_frame <evtrack.tracking.tracker.Tracker.register_frame>`
        without a box), and start every object there (:meth:`reset`).

        Returns:
            each object's :class:`~evtrack.models.mesh_registration.Registration`, by name.

        Raises:
            ValueError: an object that could not be found (named), before anything is reset.
        """
        found, starts = {}, {}
        for name, tracker in self.trackers.items():
            try:
                found[name] = tracker.register_frame(t_us, rgb, depth, None, config)
            except ValueError as exc:
                raise ValueError(f"object {name!r}: {exc}") from None
            starts[name] = tracker.T_event_rgb.numpy() @ found[name].pose
        self.reset(int(t_us), starts)
        return found

    def _start(self, t_us: int) -> None:
        self._origin = t_us
        for tracker in self.trackers.values():
            if tracker.now_us is None:
                tracker.advance(t_us)

    @property
    def names(self) -> list[str]:
        """The objects' names, in order."""
        return [o.name for o in self.objects]

    def pose(self, name: str, t_us: int | None = None) -> np.ndarray:
        """Object ``name``'s pose (4, 4) at ``t_us`` (see :meth:`Tracker.pose`)."""
        return self._tracker(name).pose(t_us)

    def twist(self, name: str, t_us: int | None = None) -> np.ndarray:
        """Object ``name``'s twist (6,) at ``t_us`` (see :meth:`Tracker.twist`)."""
        return self._tracker(name).twist(t_us)

    def trajectory(self, name: str) -> Trajectory:
        """Object ``name``'s outputs so far (one sample per velocity step)."""
        traj = self._tracker(name).trajectory()
        traj.meta["assignment"] = self.stats.to_dict()
        traj.meta["object"] = name
        return traj

    def trajectories(self) -> dict[str, Trajectory]:
        """Every object's trajectory, by name."""
        return {name: self.trajectory(name) for name in self.names}

    def _tracker(self, name: str) -> Tracker:
        try:
            return self.trackers[name]
        except KeyError:
            raise KeyError(f"no object {name!r}; the objects are {self.names}") from None

    # ------------------------------------------------------------------ inputs
    def push_events(self, events: Events) -> None:
        """Add the next events of the stream (time-sorted): assign them to the objects and
        hand each tracker its share (see the module docstring).

        Raises:
            EventsError: unsorted events, events before earlier ones, or outside the sensor.
        """
        if not isinstance(events, Events):
            raise EventsError(f"push_events expects an Events container, got "
                              f"{type(events).__name__}")
        if not len(events):
            return
        report = events.validate(self.camera.size)
        if not report.ok:
            raise EventsError(f"push_events: {report}")
        if self._last_event_us is not None and events.t_start < self._last_event_us:
            raise EventsError(f"push_events: events from t={events.t_start} µs arrive after "
                              f"events up to t={self._last_event_us} µs (push in time order)")
        events = events.to("cpu")
        if self._origin is None:
            self._start(events.t_start)
        self._last_event_us = events.t_end
        self.stats.events += len(events)
        t = events.t
        while len(events):
            window = (int(events.t_start) - self._origin) // self.window_us
            end = self._origin + (window + 1) * self.window_us
            k = int(torch.searchsorted(t, torch.tensor([end]))[0])
            if window != self._window:
                self._open(window)
            self._dispatch(events[:k])
            events, t = events[k:], t[k:]

    def _share_unposed(self) -> None:
        """Before the next step group: of the trackers whose objects wait for their first pose,
        the first (the keeper) runs the flow on the events nobody owns and keeps the unposed
        steps; the others run none and share its kept steps (see the module docstring)."""
        if not self._shares_unposed:
            return
        waiting = [t for t in self.trackers.values() if not t.initialized]
        for tracker in self.trackers.values():
            remeasurer = tracker.motion.remeasurer
            if tracker in waiting[1:]:
                tracker.motion.events_before_pose = False
                remeasurer.keeping = False
            else:
                tracker.motion.events_before_pose = True
                remeasurer.keeping = True
        if not waiting:
            self._kept = None
            return
        keeper = waiting[0].motion.remeasurer
        if self._kept is not None and keeper.unposed is not self._kept:
            keeper.unposed = self._kept  # a new keeper goes on with the steps kept so far
        self._kept = keeper.unposed
        for tracker in waiting[1:]:
            tracker.motion.remeasurer.unposed = self._kept

    def _open(self, window: int) -> None:
        """Advance every tracker to the window's start, predict the silhouettes over it, and
        tell each tracker the nearer objects its frame alignments leave out."""
        start = self._origin + window * self.window_us
        self._share_unposed()
        self._window = window
        self.stats.windows += 1
        self._masks = []
        motions: list[Occluder | None] = []
        for tracker in self.trackers.values():
            if tracker.now_us is None or tracker.now_us < start:
                tracker.advance(start)
            mask, motion = self._predicted_mask(tracker, start)
            self._masks.append(mask)
            motions.append(motion)
        for k, tracker in enumerate(self.trackers.values()):
            nearer = (o for j, o in enumerate(motions) if o is not None and j != k
                      and (self._masks[j].depth, j) < (self._masks[k].depth, k))
            tracker.occluders = Occluders(tuple(nearer))

    def _predicted_mask(self, tracker: Tracker, start: int
                        ) -> tuple[ObjectMask, Occluder | None]:
        """The tracker's silhouette swept over ``[start, start + window)`` and its depth,
        and its predicted motion over the window (as an occluder of farther objects)."""
        pose = tracker.pose()
        if not np.isfinite(pose).all() or not tracker.initialized:
            return ObjectMask(None, np.inf), None
        twist = tracker.twist()
        now = tracker.now_us if tracker.now_us is not None else start
        if now != start and np.isfinite(twist).all():
            pose = moved_pose(pose, twist, (start - now) * 1e-6)
        poly = tracker.silhouette.polygon(pose)
        if poly is None:
            return ObjectMask(None, np.inf), None
        swept = tracker.gate.swept_mask(poly, pose, self.window_us, twist)
        return (ObjectMask(swept, float(pose[2, 3])),
                Occluder(pose, np.asarray(twist, np.float64), start, tracker.silhouette.points))

    def _dispatch(self, events: Events) -> None:
        """Assign one window's events and push each tracker its share."""
        if not len(events):
            return
        claims = event_claims(events.x.numpy(), events.y.numpy(), self._masks,
                              self.config.mask_margin_px, self.camera.size)
        owner = owners(claims, self._masks)
        self.stats.unassigned += int((owner == NO_OBJECT).sum())
        self.stats.contested += int((claims.sum(axis=0) > 1).sum())
        for k, (name, tracker) in enumerate(self.trackers.items()):
            mine = owner == k
            self.stats.per_object[name] = self.stats.per_object.get(name, 0) + int(mine.sum())
            keep = mine | (owner == NO_OBJECT)
            share = events if keep.all() else events[torch.from_numpy(keep)]
            if len(share):
                tracker.push_events(share)

    def advance(self, t_us: int) -> None:
        """Declare that every event before ``t_us`` was pushed (see :meth:`Tracker.advance`).
        The trackers advance to the last window start at or before ``t_us`` (so that the next
        window's silhouettes are those the offline run predicts); :meth:`flush` takes them to
        the end."""
        t_us = int(t_us)
        if self._origin is None:
            self._start(t_us)
        self._horizon = t_us if self._horizon is None else max(self._horizon, t_us)
        start = self._origin + ((t_us - self._origin) // self.window_us) * self.window_us
        for tracker in self.trackers.values():
            tracker.advance(start)

    def push_frame(self, t_us: int, rgb: Any = None, depth: Any = None) -> None:
        """Hand an RGB-D frame to every object's tracker (see :meth:`Tracker.push_frame`).

        A frame given as a callable is read when the first tracker needs it, once, and
        shared."""
        rgb, depth = _read_once(rgb), _read_once(depth)
        if self._origin is None:
            self._start(int(t_us))
        for tracker in self.trackers.values():
            tracker.push_frame(t_us, rgb, depth)

    def flush(self) -> None:
        """Close every step up to the latest time known (the last event or :meth:`advance`),
        in every tracker. Call it at the end of a stream."""
        ends = [t for t in (self._horizon, self._last_event_us) if t is not None]
        self._share_unposed()
        for tracker in self.trackers.values():
            if ends:
                tracker.advance(max(ends))
            tracker.flush()

    # ------------------------------------------------------------------ offline
    def track(self, sequence, progress: bool = False,
              start_poses: Mapping[str, np.ndarray] | None = None,
              start_t_us: int | None = None) -> dict[str, Trajectory]:
        """Track every object through a :class:`~evtrack.Sequence` (events and frames in time
        order, as :meth:`Tracker.track` does for one).

        Args:
            start_poses: (4, 4) start poses by object name (else the objects'
                :attr:`TrackedObject.start_pose`), at ``start_t_us``; objects without one wait
                for their pose source.
            start_t_us: the stream starts there (its earlier events and frames are left
                out); ``None``: at its start.

        Returns:
            each object's :class:`~evtrack.tracking.trajectory.Trajectory`, by name.
        """
        from contextlib import ExitStack

        from evtrack.tracking.offline import push_sequence
        from evtrack.utils import threads_per_job

        if start_poses and start_t_us is None:
            raise ConfigError("MultiTracker.track: start_poses need start_t_us")
        trackers = list(self.trackers.values())
        threads = torch.get_num_threads()
        if self.config.torch_threads > 0:
            torch.set_num_threads(threads_per_job(self.config.torch_threads))
        for tracker in trackers:  # each object's pose source in its tracker's worker
            tracker.pose_calls.in_worker = tracker.config.pose_async
        try:
            with ExitStack() as stack:
                for tracker in trackers:
                    stack.enter_context(tracker._blas)
                self.reset(start_t_us, start_poses)
                push_sequence(self, sequence, self._shared_depth_preparation(), progress,
                              start_t_us)
                return self.trajectories()
        finally:
            for tracker in trackers:
                tracker.pose_calls.in_worker = False
            torch.set_num_threads(threads)

    def _shared_depth_preparation(self):
        """The sensor depth's frame preparation when every object's tracker reads the depth
        frames the same way (same cameras): each depth frame is then carried into the event
        camera once, ahead, in the reader thread, and the map shared; else ``None``."""
        sources = [t.roi_depth.source for t in self.trackers.values()]
        if not all(t.roi_depth.sensor for t in self.trackers.values()):
            return None
        first = sources[0]
        same = all(s.camera == first.camera and s.rgb_camera == first.rgb_camera
                   and np.array_equal(s.T_event_rgb, first.T_event_rgb) for s in sources)
        return first.prepare if same else None

    @property
    def method(self) -> str:
        """The method of the first object's tracker (the progress bar's label)."""
        return f"{self.trackers[self.names[0]].method} x{len(self.objects)}"


def _read_once(frame: Any) -> Any:
    """A callable frame wrapped so that it is read at most once (the trackers share it)."""
    if not callable(frame):
        return frame
    cache: list[Any] = []

    def read() -> Any:
        if not cache:
            cache.append(frame())
        return cache[0]

    return read
