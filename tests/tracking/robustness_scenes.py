"""Scenes of the tracker robustness tests (tests/tracker/test_robustness.py).

* :func:`knot_trajectory`: a simulator trajectory (:class:`evtrack.sim.trajectory.Trajectory`)
  through given waypoints, for motions the random generator never makes (leaving the image,
  stopping for a second).
* :func:`simulate_sequence`: simulate a 128x96 sequence of the test box along a trajectory.
* :func:`noise_burst`: uniformly random events over the whole sensor (a burst, as from a flicker
  or a sensor glitch).
* :class:`VisibleOnlySource`: an oracle pose source that, like a detector, finds nothing when the
  object is not in the image.
* :func:`with_events`: a sequence with other events (the same frames and ground truth).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tracker_helpers import sim_config

from evtrack import Sequence
from evtrack.events import Events, concatenate
from evtrack.sim.engine import simulate
from evtrack.sim.objects import ObjectMesh
from evtrack.sim.trajectory import Trajectory
from evtrack.tracking.pose_sources import OraclePoseSource, PoseMeasurement
from evtrack.tracking.silhouette import Silhouette


def knot_trajectory(times: list[float], positions: list[list[float]],
                    velocities: list[list[float]], rotvecs: list[list[float]] | None = None,
                    rotvec_rates: list[list[float]] | None = None,
                    R_ref: np.ndarray | None = None) -> Trajectory:
    """A C² trajectory through waypoints (seconds, metres, m/s, rad, rad/s; K knots).

    Knots with zero velocity and rotation rate are rests (the object stops there).
    """
    P = np.asarray(positions, np.float64)
    V = np.asarray(velocities, np.float64)
    k = len(times)
    Rv = np.zeros((k, 3)) if rotvecs is None else np.asarray(rotvecs, np.float64)
    W = np.zeros((k, 3)) if rotvec_rates is None else np.asarray(rotvec_rates, np.float64)
    rest = (np.abs(V).sum(1) == 0) & (np.abs(W).sum(1) == 0)
    return Trajectory(np.asarray(times, np.float64), P, V, Rv, W,
                      np.eye(3) if R_ref is None else np.asarray(R_ref, np.float64), rest)


def simulate_sequence(obj: ObjectMesh, trajectory: Trajectory, duration: float, out: Path,
                      seed: int = 3) -> Sequence:
    """Simulate ``duration`` seconds of ``obj`` along ``trajectory`` at the tracker tests'
    settings (128x96, contrast threshold 0.5, noiseless events) and open the sequence."""
    simulate(obj, sim_config(duration, seed), out, trajectory=trajectory)
    return Sequence.load(out)


def noise_burst(sensor_size: tuple[int, int], t0_us: int, duration_us: int, rate_hz: float,
                seed: int) -> Events:
    """Uniform random events: ``rate_hz`` events per second over the whole sensor in
    ``[t0_us, t0_us + duration_us)``, random polarity, time-sorted."""
    rng = np.random.default_rng(seed)
    n = int(round(rate_hz * duration_us * 1e-6))
    w, h = sensor_size
    t = np.sort(rng.integers(t0_us, t0_us + duration_us, n))
    return Events(rng.integers(0, w, n), rng.integers(0, h, n), t,
                  rng.choice(np.array([-1, 1], np.int8), n), sensor_size)


def with_events(seq: Sequence, events: Events) -> Sequence:
    """``seq`` (frames, ground truth and mesh read from its folder) with other events."""
    return Sequence(seq.meta, events=events, rgb_times_us=seq.rgb_times_us,
                    depth_times_us=seq.depth_times_us, ground_truth=seq.ground_truth,
                    root=seq.root)


def merged(a: Events, b: Events) -> Events:
    """Two event streams merged in time order (stable: ``a`` first on ties)."""
    ev = concatenate([a, b])
    order = torch.argsort(ev.t, stable=True)
    return ev[order]


class VisibleOnlySource:
    """The oracle pose source, answering only when the true silhouette is in the image.

    A detector finds nothing when the object is outside the image; the plain oracle would
    still return its (invisible) pose.

    Args:
        oracle: the noisy oracle.
        vertices: (V, 3) object vertices; camera: the image the detector sees.
        min_visible: the share of the silhouette's area that must be inside the image.
    """

    def __init__(self, oracle: OraclePoseSource, vertices: np.ndarray, camera,
                 min_visible: float) -> None:
        self.oracle = oracle
        self.silhouette = Silhouette(vertices, camera)
        self.min_visible = min_visible
        self.calls: list[int] = []
        self.answered: list[int] = []

    def __call__(self, t_us: int, rgb=None, depth=None) -> PoseMeasurement | None:
        self.calls.append(int(t_us))
        poly = self.silhouette.polygon(self.oracle.pose_at(int(t_us)).numpy())
        if poly is None or poly.visible_fraction < self.min_visible:
            return None
        self.answered.append(int(t_us))
        return self.oracle(t_us, rgb, depth)
