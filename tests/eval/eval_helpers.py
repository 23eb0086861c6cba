"""Helpers of the evaluation tests: tiny simulated benchmarks, tiny pose-network weights,
errors computed independently of evtrack.eval."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from evtrack.sim.config import EventConfig, GroundTruthConfig, SimConfig, TrajectoryConfig
from evtrack.sim.engine import simulate
from evtrack.sim.objects import procedural_object

# 96x72 images, contrast threshold 0.5 (few events), 0.3 s: one tracker run takes ~1 s.
TINY_SIZE = (96, 72)
TINY_DURATION = 0.3
# RoIs for 96 px wide images; poses at 10 Hz arriving 100 ms late (3 poses in 0.3 s).
TINY_TRACKER_YAML = """\
flow: {roi_size: 16}
pose_rate_hz: 10.0
pose_latency_ms: 100.0
ge: {contrast: 0.5}
"""


def tiny_sim_config(preset: str, seed: int, duration: float = TINY_DURATION) -> SimConfig:
    cfg = SimConfig(duration=duration, seed=seed, trajectory=TrajectoryConfig(preset=preset),
                    events=EventConfig(threshold_on=0.5, threshold_off=0.5),
                    ground_truth=GroundTruthConfig(event_flow=False))
    return dataclasses.replace(cfg, camera=cfg.camera.resized(*TINY_SIZE))


def make_tiny_benchmark(root: Path) -> Path:
    """``root/box_regular`` and ``root/box_faster``: two tiny sequences of the procedural box."""
    box = procedural_object("box", 0)
    for preset, seed in (("regular", 1), ("faster", 2)):
        simulate(box, tiny_sim_config(preset, seed), root / f"box_{preset}")
    return root


def reference_errors(poses_est: np.ndarray, poses_true: np.ndarray) -> dict[str, float]:
    """RMSE and population σ of position (cm) and rotation (deg) errors, with numpy/scipy."""
    p = 100.0 * np.linalg.norm(poses_est[:, :3, 3] - poses_true[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", poses_true[:, :3, :3], poses_est[:, :3, :3])
    r = np.rad2deg(Rotation.from_matrix(rel).magnitude())
    return {"position_rmse_cm": float(np.sqrt(np.mean(p ** 2))), "position_std_cm": float(p.std()),
            "rotation_rmse_deg": float(np.sqrt(np.mean(r ** 2))),
            "rotation_std_deg": float(r.std())}


def save_tiny_weights(path: Path, object_name: str = "box", input_size=(72, 96)) -> Path:
    """A randomly initialised ``dope_lite_tiny`` weights file for ``object_name``."""
    import torch

    from evtrack.models import Cuboid, WeightsRecord, create, save_weights
    from evtrack.sim.objects import procedural_object

    torch.manual_seed(0)
    extents = procedural_object("box", 0).extents
    record = WeightsRecord(arch="dope_lite_tiny", object_name=object_name,
                           cuboid=Cuboid(tuple(float(v) for v in extents), (0.0, 0.0, 0.0)),
                           input_size=input_size, training_data="random init (test)")
    return save_weights(path, create("dope_lite_tiny"), record)
