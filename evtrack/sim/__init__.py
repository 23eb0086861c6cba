"""The synthetic data engine: renders, events, blurred RGB-D and ground truth.

A textured object (a mesh file, a YCB object, or a procedural box/can/bottle) moves along a
random smooth 6-DoF trajectory in front of a static camera. Renders at 500 FPS (headless
OpenGL) feed an event-camera model on log intensity; the same renders are averaged into 60 FPS
motion-blurred RGB frames with depth; poses, twists and per-event optical flow come from the
true motion. Everything is written as a :class:`evtrack.Sequence` folder.

Example:
    >>> from evtrack.sim import SimConfig, resolve_object, simulate     # doctest: +SKIP
    >>> stats = simulate(resolve_object("can"), SimConfig(duration=1.0), "out/can")

Modules: :mod:`~evtrack.sim.config` (settings), :mod:`~evtrack.sim.objects` and
:mod:`~evtrack.sim.textures` (objects), :mod:`~evtrack.sim.plane` (planes, e.g. a static
scene seen by a moving camera), :mod:`~evtrack.sim.scene` and
:mod:`~evtrack.sim.renderer` (rendering), :mod:`~evtrack.sim.trajectory` (motion),
:mod:`~evtrack.sim.esim` (events), :mod:`~evtrack.sim.frames` (RGB-D camera),
:mod:`~evtrack.sim.groundtruth` (flow, pixel speeds), :mod:`~evtrack.sim.engine` (one
sequence), :mod:`~evtrack.sim.benchmark_set` (the paper's benchmark set).
"""

from evtrack.sim.benchmark_set import benchmark_entries, make_benchmark_set
from evtrack.sim.config import (
    CameraConfig,
    EventConfig,
    FrameConfig,
    GroundTruthConfig,
    RenderConfig,
    SceneConfig,
    SimConfig,
    TrajectoryConfig,
    load_config,
)
from evtrack.sim.engine import SimulationStats, simulate
from evtrack.sim.errors import MeshFileError, RendererUnavailableError
from evtrack.sim.esim import EventSimulator, log_intensity
from evtrack.sim.groundtruth import event_flow, pixel_speeds, plot_speed_cdf, point_flow
from evtrack.sim.objects import (
    ObjectMesh,
    load_mesh,
    make_bottle,
    make_box,
    make_can,
    procedural_object,
    resolve_object,
)
from evtrack.sim.plane import facing_pose, plane_facing_camera, plane_mesh, view_plane_size
from evtrack.sim.renderer import Renderer, RenderOutput
from evtrack.sim.trajectory import Trajectory, random_trajectory, static_trajectory

__all__ = [
    "CameraConfig",
    "EventConfig",
    "EventSimulator",
    "FrameConfig",
    "GroundTruthConfig",
    "MeshFileError",
    "ObjectMesh",
    "RenderConfig",
    "RenderOutput",
    "Renderer",
    "RendererUnavailableError",
    "SceneConfig",
    "SimConfig",
    "SimulationStats",
    "Trajectory",
    "TrajectoryConfig",
    "benchmark_entries",
    "event_flow",
    "facing_pose",
    "load_config",
    "load_mesh",
    "log_intensity",
    "make_benchmark_set",
    "make_bottle",
    "make_box",
    "make_can",
    "pixel_speeds",
    "plane_facing_camera",
    "plane_mesh",
    "plot_speed_cdf",
    "point_flow",
    "procedural_object",
    "random_trajectory",
    "resolve_object",
    "simulate",
    "static_trajectory",
    "view_plane_size",
]
