"""Building the tracker's parts from its config, cameras and mesh."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.denoise import EventDenoiser
from evtrack.errors import ConfigError
from evtrack.tracking.appearance_fusion import AppearanceFusion
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.depth_fusion import DepthFusion
from evtrack.tracking.depth_sources import DepthSource, ModelDepth, SensorDepth
from evtrack.tracking.motion import MotionSource
from evtrack.tracking.pose_alignment import PoseRayAligner
from evtrack.tracking.pose_flips import HalfTurnResolver
from evtrack.tracking.pose_gate import PoseGate
from evtrack.tracking.pose_timeline import PoseTimeline

__all__ = ["load_mesh", "make_appearance_fusion", "make_denoiser", "make_depth_fusion",
           "make_depth_source", "make_pose_gate"]


def load_mesh(mesh: Any) -> tuple[Any, np.ndarray]:
    """``(ObjectMesh or None, (V, 3) float64 vertices)`` of an ObjectMesh, a mesh file (object
    frame kept: no recentring) or (V, 3) vertices.

    Raises:
        ConfigError: an array that is not (V, 3).
    """
    from evtrack.sim.objects import ObjectMesh
    from evtrack.sim.objects import load_mesh as read_mesh

    if isinstance(mesh, ObjectMesh):
        return mesh, np.asarray(mesh.vertices, np.float64)
    if isinstance(mesh, str | Path):
        m = read_mesh(mesh, recenter=False)
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


def make_depth_source(config: TrackerConfig, motion: MotionSource, mesh: Any,
                      rgb_camera: PinholeCamera, T_event_rgb: torch.Tensor) -> DepthSource:
    """The depth of the motion source's sensing camera (the event camera's, the RGB camera's
    for a frame-based one): sensor frames or the mesh rendered at the pose."""
    cam = motion.sensing_camera()
    if config.depth.source == "model":
        _needs_mesh(mesh, "depth.source 'model'")
        return ModelDepth(mesh, cam, config.depth.model_scale, config.depth.model_interval_us,
                          config.depth.patch_px, config.depth.stride_px)
    if motion.depth_from_event() is not None:  # the frames are the sensing camera's
        return SensorDepth(cam, cam, None, config.depth.patch_px, config.depth.stride_px)
    return SensorDepth(cam, rgb_camera, T_event_rgb, config.depth.patch_px,
                       config.depth.stride_px)


def make_pose_gate(config: TrackerConfig, motion: MotionSource, mesh: Any,
                   vertices: np.ndarray, depth: DepthSource,
                   T_event_rgb: torch.Tensor) -> PoseGate:
    """The pose gate, with ray alignment where there are a mesh and sensor depth."""
    sensor = isinstance(depth, SensorDepth)
    aligner = None
    if config.pose_gate.depth_align and mesh is not None and sensor:
        aligner = PoseRayAligner.from_mesh(mesh, depth.camera,
                                           max_shift_m=config.pose_gate.depth_align_max_m)
    half_turns = None
    if config.pose_gate.half_turn_axes:
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        half_turns = HalfTurnResolver(config.pose_gate.half_turn_axes, (lo + hi) / 2,
                                      config.pose_gate.half_turn_max_view_deg)
    to_depth = motion.depth_from_event()
    return PoseGate(config, motion.sensing_silhouette(), sensor, aligner, half_turns,
                    None if to_depth is None else to_depth.numpy(),
                    None if to_depth is None else T_event_rgb.numpy())


def make_depth_fusion(config: TrackerConfig, motion: MotionSource, mesh: Any,
                      depth: DepthSource, timeline: PoseTimeline,
                      past_pose: Any) -> DepthFusion | None:
    """The depth fusions (``depth_fusion.range``, ``depth_fusion.icp``), or ``None`` without one
    (or for a
    method whose poses only initialise)."""
    if motion.poses_only_initialise or not (config.depth_fusion.range or config.uses_depth_icp):
        return None
    if config.depth_fusion.range:
        _needs_mesh(mesh, "depth_fusion.range")
    if config.uses_depth_icp:
        _needs_mesh(mesh, "depth_fusion.icp" if config.depth_fusion.icp else "pose_source: model")
    # the depth maps are in the sensing camera, the filter's pose in the event camera
    to_depth = motion.depth_from_event()
    T = torch.eye(4, dtype=torch.float64) if to_depth is None else to_depth
    return DepthFusion(config, mesh, depth.camera, T.numpy(), timeline, past_pose)


def make_appearance_fusion(config: TrackerConfig, motion: MotionSource, mesh: Any,
                           rgb_camera: PinholeCamera, T_event_rgb: torch.Tensor,
                           timeline: PoseTimeline, past_pose: Any) -> AppearanceFusion | None:
    """The appearance alignment (``appearance``, ``pose_source: model``), or ``None`` without
    one (or for a method whose poses only initialise)."""
    if motion.poses_only_initialise or not config.uses_appearance:
        return None
    _needs_mesh(mesh, "appearance.enabled" if config.appearance.enabled
                else "pose_source: model")
    return AppearanceFusion(config, mesh, rgb_camera, T_event_rgb.numpy(), timeline, past_pose)


def make_denoiser(cfg: TrackerConfig, motion: MotionSource, camera: PinholeCamera
                  ) -> EventDenoiser | None:
    """The event denoiser of ``cfg.denoise``, or ``None`` when it removes nothing or the
    motion source uses no events."""
    if not (cfg.denoise.enabled and motion.uses_events):
        return None
    return EventDenoiser(cfg.denoise, sensor_size=camera.size)
