"""Orchestration: object + trajectory -> renders -> events, blurred RGB-D, ground truth -> Sequence.

One pass over the render times (``render_hz``, 500 by default; optionally refined adaptively)
does everything in a stream, so memory does not grow with the number of renders:

1. render RGB, depth and mask at the true pose;
2. feed the log luminance to the :class:`~evtrack.sim.esim.EventSimulator` and compute the
   ground-truth flow of the new events from the two renders around them;
3. add base-grid renders to the current RGB exposure; at its end, add noise, encode sRGB and
   write the frame; write the depth frame of the render nearest the RGB timestamp;
4. record the pose and twist at every render.

Output: a sequence folder (:class:`evtrack.sequence.SequenceWriter`) with ``object.glb``, the
object's mesh in the object frame the poses use.

Several objects (a list of meshes): each moves on its own trajectory, laid out by
``trajectory.layout`` (:mod:`evtrack.sim.layout`), and all are drawn in every render. The
first is the sequence's object (``object.glb``, ``groundtruth.h5``); object ``k >= 1`` has
``objects/k/object.glb`` and ``objects/k/groundtruth.h5``, listed in ``meta.yaml``'s
``objects``. ``groundtruth.h5`` then also holds, per event, the object it is on
(``event_object``) and its flow from that object's motion.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from evtrack.events import Events, concatenate
from evtrack.sequence import GT_FILE, GroundTruth, SequenceMeta, SequenceObject, SequenceWriter
from evtrack.sim.config import SimConfig, TrajectoryConfig
from evtrack.sim.esim import EventSimulator, log_intensity
from evtrack.sim.frames import (
    ExposureAccumulator,
    ExposureWindow,
    add_depth_noise,
    add_rgb_noise,
    exposure_windows,
    linear_to_srgb,
)
from evtrack.sim.groundtruth import (
    event_flow,
    labelled_event_flow,
    pixel_speeds,
    speed_percentiles,
)
from evtrack.sim.layout import object_trajectories
from evtrack.sim.objects import ObjectMesh
from evtrack.sim.renderer import Renderer
from evtrack.sim.scene import Scene, build_scene
from evtrack.sim.trajectory import Trajectory, random_trajectory

__all__ = [
    "simulate",
    "SimulationStats",
    "render_times_us",
    "MESH_FILE",
    "preset_config",
    "sequence_scene",
    "sequence_trajectory",
    "sequence_trajectories",
    "speed_samples",
]

MESH_FILE = "object.glb"
_FLUSH_EVENTS = 2_000_000  # events buffered before a write to events.h5

@dataclass
class SimulationStats:
    """What a simulation produced, and how long each stage took (seconds; not stored)."""

    num_renders: int = 0
    num_base_renders: int = 0
    num_events: int = 0
    num_rgb: int = 0
    subdivided_intervals: int = 0
    capped_intervals: int = 0
    pixel_speed: dict[str, float] = field(default_factory=dict)
    pixel_speed_samples: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        return {
            "renders": self.num_renders,
            "base_renders": self.num_base_renders,
            "events": self.num_events,
            "rgb_frames": self.num_rgb,
            "subdivided_intervals": self.subdivided_intervals,
            "intervals_at_subdivision_limit": self.capped_intervals,
            "pixel_speed_px_s": self.pixel_speed,
        }


@dataclass
class _RenderState:
    t_us: int
    log: torch.Tensor      # (H, W) on the simulator's device
    depth: np.ndarray      # (H, W) float32 metres, 0 = nothing
    mask: np.ndarray       # (H, W) bool
    labels: np.ndarray | None = None  # (H, W) int16 object labels, several objects only


def render_times_us(duration_s: float, render_hz: float) -> np.ndarray:
    """Base-grid render times ``round(k · 1e6 / render_hz)`` µs up to the duration."""
    duration_us = int(round(duration_s * 1e6))
    count = int(np.floor(duration_us * render_hz / 1e6 + 1e-9)) + 1
    return np.round(np.arange(count) * 1e6 / render_hz).astype(np.int64)


class _Timer:
    def __init__(self) -> None:
        self.totals: dict[str, float] = {}

    def __call__(self, name: str):
        timer = self

        class _Ctx:
            def __enter__(self):
                self.t = time.perf_counter()

            def __exit__(self, *exc):
                timer.totals[name] = timer.totals.get(name, 0.0) + time.perf_counter() - self.t

        return _Ctx()


_STREAMS = ("trajectory", "scene", "events", "rgb_noise", "depth_noise")


def _seeds(seed: int) -> dict[str, np.random.SeedSequence]:
    return dict(zip(_STREAMS, np.random.SeedSequence(int(seed)).spawn(len(_STREAMS)),
                    strict=True))


def _object_trajectory_seeds(seed: int, count: int) -> list[np.random.SeedSequence]:
    """Object 0's trajectory stream is the one-object stream; object ``k >= 1`` gets a child
    spawned after the named streams (the named streams do not change)."""
    children = np.random.SeedSequence(int(seed)).spawn(len(_STREAMS) + count - 1)
    return [children[0]] + children[len(_STREAMS):]


def sequence_scene(config: SimConfig) -> Scene:
    """The static scene :func:`simulate` uses for ``config`` (drawn from its seed)."""
    seeds = _seeds(config.seed)
    return build_scene(config.scene, config.camera.camera(), np.random.default_rng(seeds["scene"]))


def sequence_trajectory(config: SimConfig, obj: ObjectMesh) -> Trajectory:
    """The random trajectory :func:`simulate` uses for ``config`` and ``obj``."""
    seeds = _seeds(config.seed)
    return random_trajectory(config.duration, config.camera.camera(), obj.radius,
                             config.trajectory, seed=seeds["trajectory"])


def sequence_trajectories(config: SimConfig, objects: list[ObjectMesh]) -> list[Trajectory]:
    """The random trajectories :func:`simulate` uses for several ``objects`` (one object:
    :func:`sequence_trajectory`'s)."""
    if len(objects) == 1:
        return [sequence_trajectory(config, objects[0])]
    return object_trajectories(config.duration, config.camera.camera(),
                               [o.radius for o in objects], config.trajectory,
                               _object_trajectory_seeds(config.seed, len(objects)))


def simulate(
    obj: ObjectMesh | list[ObjectMesh],
    config: SimConfig,
    out_dir: str | Path,
    *,
    name: str | None = None,
    trajectory: Trajectory | list[Trajectory] | None = None,
    overwrite: bool = False,
    progress: bool | Callable[[int], None] = False,
    extra: Mapping[str, Any] | None = None,
) -> SimulationStats:
    """Simulate one sequence and write it to ``out_dir`` (a sequence folder).

    Args:
        obj: the tracked object, or a list of several (unique names; see the module
            docstring).
        config: camera, scene, timing, trajectory preset, event model, frames, seed.
        out_dir: the sequence folder to create (it appears only when complete).
        name: sequence name (default: the folder name).
        trajectory: use this trajectory instead of a random one (e.g. a static one); with
            several objects a list of one per object.
        overwrite: replace an existing folder.
        progress: show a tqdm bar (``True``) or call ``progress(n)`` after ``n`` more
            base renders.
        extra: more entries of ``meta.yaml``'s ``extra`` (e.g. ``benchmark``: the sequence's
            place in a benchmark split); they may not replace the simulator's own entries.

    Returns:
        counts, pixel-speed statistics and stage timings (seconds).

    Raises:
        ValueError: ``extra`` names an entry the simulator writes itself; several objects
            share a name; a trajectory list of another length than the objects'.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise FileExistsError(f"{out_dir} exists; pass overwrite=True to replace it")
    clash = sorted(set(extra or {}) & set(SIM_EXTRA_KEYS))
    if clash:
        raise ValueError(f"extra entries {clash} are the simulator's own meta.yaml entries")
    t_start = time.perf_counter()
    run = _Simulation(obj, config, name or out_dir.name, trajectory)
    run.more_extra = dict(extra or {})
    bar = None
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=len(run.base_times), unit="render", desc=f"simulate {run.meta.name}")
    tick = bar.update if bar is not None else (progress if callable(progress) else None)

    renderer = Renderer(run.cam, config.render.near, config.render.far)
    threads_before = torch.get_num_threads()
    if config.torch_threads > 0:
        torch.set_num_threads(config.torch_threads)
    try:
        run.prepare(renderer)
        with SequenceWriter(out_dir, run.meta, overwrite=overwrite) as writer:
            run.write(writer, tick)
    finally:
        torch.set_num_threads(threads_before)
        renderer.release()
        if bar is not None:
            bar.close()
    stats = run.stats
    stats.timings = dict(run.timer.totals)
    total = time.perf_counter() - t_start
    stats.timings["other"] = total - sum(stats.timings.values())  # set-up, closing files
    stats.timings["total"] = total
    return stats


class _Simulation:
    """One :func:`simulate` run: its schedule, random streams, and the state of the stream of
    renders (events waiting to be written, the open exposure, the ground truth so far)."""

    def __init__(self, obj: ObjectMesh | list[ObjectMesh], config: SimConfig, name: str,
                 trajectory: Trajectory | list[Trajectory] | None) -> None:
        self.objects = list(obj) if isinstance(obj, list | tuple) else [obj]
        if not self.objects:
            raise ValueError("simulate: give at least one object")
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise ValueError(f"simulate: the objects' names must be unique, got {names}")
        self.multi = len(self.objects) > 1
        self.obj, self.config = self.objects[0], config
        self.timer = _Timer()
        self.cam = cam = config.camera.camera()
        seeds = _seeds(config.seed)
        duration_us = int(round(config.duration * 1e6))
        if trajectory is None:
            trajectories = sequence_trajectories(config, self.objects)
        else:
            trajectories = list(trajectory) if isinstance(trajectory, list | tuple) else [
                trajectory]
        if len(trajectories) != len(self.objects):
            raise ValueError(f"simulate: {len(trajectories)} trajectories for "
                             f"{len(self.objects)} objects")
        self.trajectories = trajectories
        self.trajectory = trajectories[0]
        self.scene = sequence_scene(config)
        self.base_times = render_times_us(config.duration, config.render.render_hz)
        windows = exposure_windows(self.base_times, config.frames.rgb_hz,
                                   config.frames.exposure, duration_us)
        self.frame_of_render, self.depth_render = _frame_schedule(windows, self.base_times)
        self.esim = EventSimulator(cam.width, cam.height, config.events,
                                   seed=int(seeds["events"].generate_state(1)[0]))
        self.rgb_rng = np.random.default_rng(seeds["rgb_noise"])
        self.depth_rng = np.random.default_rng(seeds["depth_noise"])
        self.stats = SimulationStats(num_base_renders=len(self.base_times))
        self.pose_times: list[int] = []
        self.flows: list[np.ndarray] = []
        self.owners: list[np.ndarray] = []
        self.pending: list[Events] = []
        self.pending_n = 0
        self.acc = ExposureAccumulator()
        self.min_threshold = min(config.events.threshold_on, config.events.threshold_off)
        self.meta = SequenceMeta(
            event_camera=cam, name=name, object_name=self.obj.name, mesh_path=MESH_FILE,
            rgb_camera=cam, rates={"render_hz": config.render.render_hz,
                                   "rgb_hz": config.frames.rgb_hz,
                                   "depth_hz": config.frames.rgb_hz},
            depth_unit="mm_png16", source="simulation",
            objects=[SequenceObject(o.name, *_object_files(k)) for k, o in enumerate(
                self.objects)] if self.multi else [])
        self.more_extra: dict[str, Any] = {}
        self.renderer: Renderer
        self.writer: SequenceWriter

    def prepare(self, renderer: Renderer) -> None:
        """Set up ``renderer`` with the scene and the object."""
        self.renderer = renderer
        self.scene.apply(renderer)
        renderer.set_objects(self.objects)

    def write(self, writer: SequenceWriter, tick: Callable[[int], Any] | None) -> None:
        """Render every base time (and the adaptive midpoints); write the events, frames,
        ground truth and mesh."""
        self.writer = writer
        prev = self.render(int(self.base_times[0]), 0)
        self.esim.reset(prev.log, prev.t_us)
        self.pose_times.append(prev.t_us)
        if tick:
            tick(1)
        for k in range(1, len(self.base_times)):
            cur = self.render(int(self.base_times[k]), k)
            self.step(prev, cur, 0)
            prev = cur
            if tick:
                tick(1)
        self.flush()
        self.write_ground_truth()
        self.meta.extra = _extra(self.config, self.obj, self.trajectory, self.scene, self.stats)
        if self.multi:
            self.meta.extra["objects"] = [
                {"name": o.name, "source": o.source, "offset": [float(v) for v in o.offset],
                 "trajectory": tr.to_dict()}
                for o, tr in zip(self.objects, self.trajectories, strict=True)]
            self.meta.extra["event_object"] = (
                "index in objects of the object each event is on, -1 for none")
        self.meta.extra.update(self.more_extra)
        with self.timer("write"):
            for k, o in enumerate(self.objects):
                o.export(writer.file_path(_object_files(k)[0]))

    def render(self, t_us: int, base_index: int | None = None) -> _RenderState:
        """Render at ``t_us``; a base render (``base_index``) also feeds the frames."""
        with self.timer("render"):
            raw = self.renderer.render_raw([tr.pose(t_us * 1e-6) for tr in self.trajectories])
            w = raw[..., 3]
            depth = np.abs(w)
            mask = w > 0
            labels = self.renderer.labels() if self.multi else None
        if base_index is not None:
            self.frames(base_index, t_us, raw, depth)
        with self.timer("events"):
            log = log_intensity(torch.from_numpy(raw[..., :3]).to(self.esim.device),
                                self.config.events.log_eps)
        return _RenderState(int(t_us), log, depth, mask, labels)

    def step(self, a: _RenderState, b: _RenderState, level: int) -> None:
        """The events from ``a`` to ``b``, after splitting the interval where the adaptive
        rendering asks for it (``level``: splits so far)."""
        render = self.config.render
        if (render.adaptive and b.t_us - a.t_us >= 2
                and _too_big(a, b, render.depth_jump,
                             render.max_log_change * self.min_threshold)):
            if level < render.max_subdivisions:
                if level == 0:
                    self.stats.subdivided_intervals += 1
                mid = self.render((a.t_us + b.t_us) // 2)
                self.step(a, mid, level + 1)
                self.step(mid, b, level + 1)
                return
            self.stats.capped_intervals += 1
        self.emit(a, b)

    def emit(self, a: _RenderState, b: _RenderState) -> None:
        """Step the event simulator to ``b``; its events (and their flow) join the queue."""
        with self.timer("events"):
            ev = self.esim.step(b.log, b.t_us).to("cpu")
        self.pose_times.append(b.t_us)
        if not len(ev):
            return
        if self.multi:
            with self.timer("ground_truth"):
                flow, owner = labelled_event_flow(
                    ev.x.numpy(), ev.y.numpy(), ev.t.numpy(), a.t_us, a.depth, a.labels,
                    b.t_us, b.depth, b.labels, self.trajectories, self.cam)
                self.owners.append(owner)
                if self.config.ground_truth.event_flow:
                    self.flows.append(flow)
        elif self.config.ground_truth.event_flow:
            with self.timer("ground_truth"):
                self.flows.append(event_flow(
                    ev.x.numpy(), ev.y.numpy(), ev.t.numpy(), a.t_us, a.depth, a.mask,
                    b.t_us, b.depth, b.mask, self.trajectory, self.cam))
        self.pending.append(ev)
        self.pending_n += len(ev)
        self.stats.num_events += len(ev)
        if self.pending_n >= _FLUSH_EVENTS:
            self.flush()

    def flush(self) -> None:
        """Write the queued events."""
        if self.pending:
            with self.timer("write"):
                self.writer.add_events(concatenate(self.pending))
            self.pending, self.pending_n = [], 0

    def frames(self, k: int, t_us: int, raw: np.ndarray, depth: np.ndarray) -> None:
        """Base render ``k`` into the open RGB exposure (a frame when it closes) and, if it is
        the one nearest a frame's timestamp, into a depth frame."""
        frames = self.config.frames
        with self.timer("frames"):
            w = self.frame_of_render.get(k)
            if w is not None:
                self.acc.add(raw)  # the whole RGBA buffer: contiguous, fast; alpha unused
                if k == w.last:
                    noisy = add_rgb_noise(self.acc.mean()[..., :3], self.rgb_rng, frames)
                    self.writer.add_rgb(w.t_us, linear_to_srgb(noisy))
                    self.acc.reset()
                    self.stats.num_rgb += 1
            if k in self.depth_render:
                self.writer.add_depth(t_us, add_depth_noise(depth, self.depth_rng, frames,
                                                            self.cam.fx))

    def write_ground_truth(self) -> None:
        """Poses and twists at every render, the events' flow, the pixel-speed statistics."""
        with self.timer("ground_truth"):
            t_us = np.asarray(self.pose_times, np.int64)
            poses = self.trajectory.pose(t_us * 1e-6)
            twists = self.trajectory.twist(t_us * 1e-6)
            flow = None
            if self.config.ground_truth.event_flow:
                flow = (np.concatenate(self.flows) if self.flows
                        else np.zeros((0, 2), np.float32))
            owner = None
            if self.multi:
                owner = (np.concatenate(self.owners) if self.owners
                         else np.zeros(0, np.int16))
            self.writer.set_ground_truth(GroundTruth(t_us, poses, t_us, twists, flow, owner))
            for k, tr in enumerate(self.trajectories[1:], start=1):
                GroundTruth(t_us, tr.pose(t_us * 1e-6), t_us, tr.twist(t_us * 1e-6)).save(
                    self.writer.file_path(_object_files(k)[1]))
            samples = speed_samples(self.obj, self.trajectory, t_us, self.cam,
                                    self.config.ground_truth.velocity_samples)
        self.stats.num_renders = len(self.pose_times)
        self.stats.pixel_speed = speed_percentiles(samples)
        self.stats.pixel_speed_samples = samples


def _object_files(index: int) -> tuple[str, str]:
    """Object ``index``'s mesh and ground-truth files in a sequence folder."""
    if index == 0:
        return MESH_FILE, GT_FILE
    return f"objects/{index}/{MESH_FILE}", f"objects/{index}/{GT_FILE}"


def _frame_schedule(windows: list[ExposureWindow], base_times: np.ndarray
                    ) -> tuple[dict[int, ExposureWindow], dict[int, ExposureWindow]]:
    """For each base render index: the RGB exposure window it belongs to, and the window whose
    depth frame it gives (the render nearest the window's timestamp)."""
    frame_of_render = {}
    depth_render = {}
    for w in windows:
        for k in range(w.first, w.last + 1):
            frame_of_render[k] = w
        ks = np.arange(w.first, w.last + 1)
        depth_render[int(ks[np.argmin(np.abs(base_times[ks] - w.t_us))])] = w
    return frame_of_render, depth_render


def _too_big(a: _RenderState, b: _RenderState, depth_jump: float, limit: float) -> bool:
    """Whether some pixel's log intensity changes by more than ``limit`` between renders,
    ignoring pixels where the visible surface changes (coverage flip or depth jump)."""
    change = (b.log - a.log).abs()
    same = torch.from_numpy((a.mask == b.mask) & (np.abs(a.depth - b.depth) <= depth_jump))
    change = change[same.to(change.device)]
    return bool(change.numel()) and float(change.max()) > limit


def speed_samples(obj: ObjectMesh, trajectory: Trajectory, t_us: np.ndarray, camera,
                  count: int) -> np.ndarray:
    """Mean pixel speed (px/s) of ``count`` evenly picked mesh vertices at each time (µs)."""
    idx = np.linspace(0, len(obj.vertices) - 1, min(count, len(obj.vertices))).astype(int)
    return pixel_speeds(trajectory, np.asarray(t_us) * 1e-6,
                        obj.vertices[idx].astype(np.float64), camera)


SIM_EXTRA_KEYS = ("generator", "seed", "config", "object", "trajectory", "scene",
                  "rgb_timestamps", "depth_timestamps", "event_order", "event_flow", "stats",
                  "objects", "event_object")
"""The entries of ``meta.yaml``'s ``extra`` the simulator writes (see :func:`_extra`)."""


def _extra(config: SimConfig, obj: ObjectMesh, trajectory: Trajectory, scene,
           stats: SimulationStats) -> dict[str, Any]:
    from evtrack import __version__

    return {
        "generator": f"evtrack.sim {__version__}",
        "seed": config.seed,
        "config": config.to_dict(),
        "object": {
            "source": obj.source,
            "frame": "source mesh translated by -offset (bounding-box centre), axes and "
                     "metres kept; object.glb holds the mesh in this frame",
            "offset": [float(v) for v in obj.offset],
        },
        "trajectory": trajectory.to_dict(),
        "scene": scene.describe(),
        "rgb_timestamps": "mean time of the renders averaged into each frame",
        "depth_timestamps": "time of the render used (nearest to the RGB frame's timestamp)",
        "event_order": "by time; ties: within a render interval by pixel index y*W+x, then "
                       "crossing order",
        "event_flow": "px/s at each event from the true twist and rendered depth; NaN off "
                      "the object",
        "stats": stats.summary(),
    }


def preset_config(base: SimConfig, preset: str) -> SimConfig:
    """``base`` with the trajectory speeds of ``preset`` (other trajectory fields kept)."""
    import dataclasses

    tr = base.trajectory
    fields = {f.name: getattr(tr, f.name) for f in dataclasses.fields(tr)}
    fields.update(preset=preset, linear_speed=None, angular_speed=None)
    return dataclasses.replace(base, trajectory=TrajectoryConfig(**fields))
