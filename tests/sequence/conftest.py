"""Fixtures of the sequence tests: a small in-memory sequence with ground truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack import Events, PinholeCamera, Sequence
from evtrack.geometry import integrate_twist, tq_to_matrix
from evtrack.sequence import GroundTruth, SequenceMeta


def make_sequence(n_events: int = 2000, n_frames: int = 3, seed: int = 0) -> Sequence:
    g = np.random.default_rng(seed)
    cam = PinholeCamera(100.0, 100.0, 31.5, 23.5, 64, 48)
    ev = Events(g.integers(0, 64, n_events), g.integers(0, 48, n_events),
                np.sort(g.integers(0, 50_000, n_events)), g.choice([-1, 1], n_events),
                sensor_size=(64, 48))
    rgb = g.integers(0, 256, (n_frames, 48, 64, 3), dtype=np.uint8)
    depth = g.uniform(0.4, 1.2, (n_frames, 48, 64)).astype(np.float32)
    depth[:, :2, :2] = 0.0  # holes
    t_frames = torch.arange(n_frames) * 16_667
    T0 = tq_to_matrix(torch.tensor([0.0, 0.0, 0.8], dtype=torch.float64),
                      torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64))
    V = torch.tensor([0.1, -0.2, 0.05, 0.5, 1.0, -0.3], dtype=torch.float64)
    ts = torch.arange(0, 50_001, 2000)
    poses = integrate_twist(T0.expand(len(ts), 4, 4), V.expand(len(ts), 6), ts * 1e-6)
    gt = GroundTruth(ts, poses, ts, V.expand(len(ts), 6),
                     event_flow=torch.from_numpy(g.normal(size=(n_events, 2))).float())
    meta = SequenceMeta(event_camera=cam, name="unit", object_name="box", mesh_path="box.obj",
                        rgb_camera=cam, rates={"rgb_hz": 60.0}, source="simulation",
                        extra={"seed": seed, "array": np.arange(3)})
    return Sequence(meta, ev, t_frames, rgb, t_frames, depth, gt)


@pytest.fixture
def sequence_factory():
    """``make_sequence(n_events=2000, n_frames=3, seed=0) -> Sequence``."""
    return make_sequence
