"""Pose accuracy of a tracked trajectory as 6-DoF trackers report it beside the RMSE: the ADD
and ADD-S AUC up to 10 % of the object's diameter, and the share within 5 cm and 5°.

Per ground-truth sample:

* **ADD**: the mean distance (m) between the model points moved by the estimated and by the
  true pose (:func:`~evtrack.eval.pose_metrics.add_distances`).
* **ADD-S**: the mean distance (m) from each truly-posed model point to the *nearest*
  estimated-posed one (:func:`~evtrack.eval.pose_metrics.adds_distances`). A pose that differs
  from the truth by a symmetry of the object (a can turned about its axis, a box by 180°)
  scores 0, so ADD-S is the fair one for symmetric objects; ADD is the strict one, and both
  are reported for every object.
* **AUC**: the area under the accuracy-threshold curve (the share of samples whose error is
  below ``τ``) for ``τ`` from 0 to ``τ_max = 0.1 d``, ``d`` the object's diameter, normalised
  to 0-100 %. A sample at error ``e`` is accurate for every ``τ`` in ``(e, τ_max]``, a part
  ``max(0, 1 - e / τ_max)`` of the range, so the continuous AUC is exactly
  ``100 · mean_i max(0, 1 - e_i / τ_max)`` (:func:`auc_percent`).
* **5 cm / 5°**: the share (%) of samples whose position error is below 5 cm and whose
  rotation error is below 5°, both at once (the errors of :mod:`evtrack.eval.metrics`).

Samples and failures: the samples are the ground truth's own (its stored poses, e.g. 500 Hz
in a simulated sequence), every one in the evaluated span (by default the whole sequence), as
the field scores annotated frames. The estimate at a ground-truth time ``t`` is the tracker's
latest output: the trajectory sample at or just before ``t`` (the trajectory has one per
velocity step, 1 ms apart by default). A sample without an estimate is a failure, with error
``∞``: it adds 0 to the AUC and fails 5 cm / 5°. That is a time before the trajectory's first
sample, or whose latest sample is not tracking (before the first pose, or while the object was
lost) or has a non-finite pose. So these scores fall with the share tracked, unlike the RMSE,
which is taken over the tracked samples only (and at the trajectory's times, the ground truth
interpolated there: :func:`~evtrack.eval.metrics.tracking_errors`).

Model points: the vertices of the sequence's mesh in the object frame of the ground-truth poses
(not recentred). The means of ADD and ADD-S run over at most :data:`MAX_MODEL_POINTS` of them,
picked evenly through the vertex list (deterministic); ADD-S searches each point's nearest
among *all* the vertices, since a sparser set leaves it closer to ADD (on a tracked sequence
of the YCB cracker box, the ADD-S AUC came out 6 points lower with 1000 vertices searched than
with all 8427, and within 0.3 points with 1000 averaged over and all searched). So they estimate
the scores of the whole vertex set, at the cost of 1000 nearest-point queries per sample: a
second or two for a 2 s sequence (1000 ground-truth samples). The diameter is the largest
distance between two vertices of the whole mesh.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from evtrack.eval.metrics import position_errors, rotation_errors
from evtrack.eval.pose_metrics import add_distances, adds_distances, object_diameter
from evtrack.tracking.trajectory import Trajectory

__all__ = ["AUC_FRACTION", "MAX_MODEL_POINTS", "WITHIN_M", "WITHIN_DEG", "ObjectModel",
           "object_model", "auc_percent", "within_percent", "PoseScores", "estimates_at",
           "pose_scores", "sequence_pose_scores"]

AUC_FRACTION = 0.1
"""The AUC's largest threshold as a fraction of the object's diameter."""

MAX_MODEL_POINTS = 1000
"""Model points at most that ADD / ADD-S average over (picked evenly from the mesh's
vertices)."""

WITHIN_M = 0.05
"""Position error (m) below which a sample passes 5 cm / 5°."""

WITHIN_DEG = 5.0
"""Rotation error (deg) below which a sample passes 5 cm / 5°."""


@dataclass(frozen=True)
class ObjectModel:
    """The model points of ADD / ADD-S and the object's diameter.

    Attributes:
        points: (M, 3) float64 points ADD and ADD-S average over, object frame, metres.
        vertices: (V, 3) float64 all the mesh's vertices (``points`` among them), where ADD-S
            searches the nearest, object frame, metres.
        diameter_m: largest distance between two vertices, metres.
    """

    points: np.ndarray
    vertices: np.ndarray
    diameter_m: float


def object_model(vertices: np.ndarray, max_points: int = MAX_MODEL_POINTS) -> ObjectModel:
    """Model points and diameter of a mesh's vertices.

    Args:
        vertices: (V, 3) vertices in the object frame, metres.
        max_points: at most this many points to average over, picked evenly through the
            vertex list (all of them when there are fewer).

    Raises:
        ValueError: not (V, 3) with V >= 2, or ``max_points < 1``.
    """
    vertices = np.asarray(vertices, np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 2:
        raise ValueError(f"need (V, 3) vertices with V >= 2, got shape {vertices.shape}")
    if max_points < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    if len(vertices) > max_points:
        idx = np.unique(np.linspace(0, len(vertices) - 1, max_points).round().astype(np.int64))
        points = vertices[idx]
    else:
        points = vertices
    return ObjectModel(points, vertices, object_diameter(vertices))


def auc_percent(errors: np.ndarray, max_threshold: float) -> float:
    """AUC (%) of the accuracy over thresholds 0 to ``max_threshold``.

    Args:
        errors: (N,) per-sample errors (ADD or ADD-S, metres); ``inf`` or NaN for a failure.
        max_threshold: the largest threshold ``τ_max`` (metres), > 0.

    Returns:
        ``100 · mean_i max(0, 1 - e_i / τ_max)``, the exact area under the curve
        ``τ ↦ share of samples with e_i < τ`` over ``[0, τ_max]``, divided by ``τ_max``;
        NaN for no samples.
    """
    if not (math.isfinite(max_threshold) and max_threshold > 0):
        raise ValueError(f"the largest threshold must be finite and > 0, got {max_threshold}")
    e = np.asarray(errors, np.float64).reshape(-1)
    if e.size == 0:
        return math.nan
    score = np.where(np.isfinite(e), np.clip(1.0 - e / max_threshold, 0.0, 1.0), 0.0)
    return float(100.0 * score.mean())


def within_percent(position_m: np.ndarray, rotation_deg: np.ndarray,
                   max_m: float = WITHIN_M, max_deg: float = WITHIN_DEG) -> float:
    """Share (%) of samples with position error < ``max_m`` and rotation error < ``max_deg``.

    Args:
        position_m: (N,) position errors, metres (``inf`` or NaN: a failure).
        rotation_deg: (N,) rotation errors, degrees (``inf`` or NaN: a failure).

    Returns:
        a percentage; NaN for no samples.
    """
    p = np.asarray(position_m, np.float64).reshape(-1)
    r = np.asarray(rotation_deg, np.float64).reshape(-1)
    if p.shape != r.shape:
        raise ValueError(f"{p.size} position errors for {r.size} rotation errors")
    if p.size == 0:
        return math.nan
    return float(100.0 * np.mean((p < max_m) & (r < max_deg)))


@dataclass
class PoseScores:
    """ADD / ADD-S AUC and the 5 cm / 5° share of one trajectory.

    Attributes:
        add_auc, adds_auc: AUC (%) of ADD and of ADD-S up to :data:`AUC_FRACTION` of the
            diameter, over every ground-truth sample of the evaluated span (NaN when not
            computed).
        within_5cm_5deg: share (%) of those samples within 5 cm and 5° (NaN when not computed).
        diameter_m: the object's diameter, metres (NaN without a mesh).
        samples: ground-truth samples of the evaluated span (the untracked ones included).
        tracked: those with an estimate (the latest trajectory sample tracking, finite pose).
        points: model points ADD / ADD-S averaged over.
        note: why the scores are NaN (``""`` when they were computed).
    """

    add_auc: float
    adds_auc: float
    within_5cm_5deg: float
    diameter_m: float
    samples: int
    tracked: int
    points: int
    note: str = ""

    @property
    def threshold_m(self) -> float:
        """The AUC's largest threshold, metres (:data:`AUC_FRACTION` x diameter)."""
        return AUC_FRACTION * self.diameter_m

    @classmethod
    def unavailable(cls, samples: int, note: str) -> PoseScores:
        """Scores that could not be computed (all NaN), and why."""
        nan = math.nan
        return cls(nan, nan, nan, nan, int(samples), 0, 0, note)

    def to_dict(self) -> dict[str, float | int | str]:
        return asdict(self)

    def __str__(self) -> str:
        if self.note:
            return f"ADD / ADD-S AUC and 5 cm / 5°: not computed ({self.note})"
        return (f"ADD AUC {self.add_auc:.1f}%  ADD-S AUC {self.adds_auc:.1f}%  "
                f"5cm/5° {self.within_5cm_5deg:.1f}%  [d = {100 * self.diameter_m:.1f} cm, "
                f"{self.tracked}/{self.samples} samples tracked]")


def _span(t_us: torch.Tensor, t_start_us: int | None, t_end_us: int | None) -> torch.Tensor:
    """(n,) bool: the times ``t_start_us <= t_us <= t_end_us`` (``None``: unbounded)."""
    window = torch.ones_like(t_us, dtype=torch.bool)
    if t_start_us is not None:
        window &= t_us >= int(t_start_us)
    if t_end_us is not None:
        window &= t_us <= int(t_end_us)
    return window


def estimates_at(trajectory: Trajectory, t_us: torch.Tensor) -> tuple[torch.Tensor,
                                                                      torch.Tensor]:
    """The tracker's latest output at each time: ``(index, has)``, both (n,).

    Args:
        trajectory: the tracker's output.
        t_us: (n,) int64 µs.

    Returns:
        ``index``: int64 index of the trajectory sample at or just before each time (0 where
        there is none); ``has``: bool, True where that sample exists, is tracking (status 1)
        and has a finite pose.
    """
    t_us = torch.as_tensor(t_us, dtype=torch.int64).reshape(-1)
    if len(trajectory) == 0:
        return torch.zeros_like(t_us), torch.zeros(t_us.shape, dtype=torch.bool)
    k = torch.searchsorted(trajectory.t_us, t_us, right=True) - 1
    index = k.clamp(min=0)
    finite = torch.isfinite(trajectory.poses[index]).flatten(1).all(1)
    return index, (k >= 0) & trajectory.tracked[index] & finite


def pose_scores(trajectory: Trajectory, ground_truth, model: ObjectModel,
                t_start_us: int | None = None, t_end_us: int | None = None,
                workers: int = 1) -> PoseScores:
    """ADD / ADD-S AUC and 5 cm / 5° share of a trajectory against ground truth.

    Args:
        trajectory: the tracker's output.
        ground_truth: a :class:`~evtrack.sequence.GroundTruth` (or anything with ``pose_t_us``
            (M,) int64 µs and ``poses`` (M, 4, 4) float64 object-to-camera, metres).
        model: the object's model points and diameter (:func:`object_model`).
        t_start_us, t_end_us: the evaluated span, µs (``None``: unbounded): the ground-truth
            samples with ``t_start_us <= t <= t_end_us``.
        workers: threads of the ADD-S nearest-point queries.

    Returns:
        :class:`PoseScores` over every ground-truth sample of the span, those without an
        estimate failing.
    """
    t = torch.as_tensor(ground_truth.pose_t_us, dtype=torch.int64).reshape(-1)
    window = _span(t, t_start_us, t_end_us)
    n = int(window.sum())
    if n == 0:
        scores = PoseScores.unavailable(0, "no ground-truth sample in the evaluated span")
        scores.diameter_m, scores.points = model.diameter_m, len(model.points)
        return scores
    index, has = estimates_at(trajectory, t[window])
    tracked = int(has.sum())
    add, adds = np.full(n, np.inf), np.full(n, np.inf)
    pos, rot = np.full(n, np.inf), np.full(n, np.inf)
    if tracked:
        est = trajectory.poses[index[has]]
        true = torch.as_tensor(ground_truth.poses, dtype=torch.float64)[window][has]
        mask = has.numpy()
        add[mask] = add_distances(est.numpy(), true.numpy(), model.points)
        adds[mask] = adds_distances(est.numpy(), true.numpy(), model.points, workers=workers,
                                    targets=model.vertices)
        pos[mask] = position_errors(est, true).numpy()
        rot[mask] = np.rad2deg(rotation_errors(est, true).numpy())
    tau = AUC_FRACTION * model.diameter_m
    return PoseScores(auc_percent(add, tau), auc_percent(adds, tau), within_percent(pos, rot),
                      model.diameter_m, n, tracked, len(model.points))


def sequence_pose_scores(trajectory: Trajectory, sequence, t_start_us: int | None = None,
                         t_end_us: int | None = None, workers: int = 1,
                         max_points: int = MAX_MODEL_POINTS) -> PoseScores:
    """:func:`pose_scores` with the model and ground truth of a :class:`~evtrack.Sequence`.

    The model points come from the sequence's mesh (``meta.yaml`` ``object.mesh``), read in the
    object frame of its ground-truth poses. A sequence without a mesh or ground truth, or whose
    mesh cannot be read, gets NaN scores whose ``note`` says why (not an error).
    """
    from evtrack.sim.errors import MeshFileError
    from evtrack.sim.objects import load_mesh

    gt = sequence.ground_truth
    if gt is None:
        return PoseScores.unavailable(0, "the sequence has no ground truth")
    samples = int(_span(gt.pose_t_us, t_start_us, t_end_us).sum())
    mesh: Path | None = sequence.mesh_file
    if mesh is None:
        return PoseScores.unavailable(samples, "the sequence names no object mesh "
                                      "(meta.yaml object.mesh)")
    try:
        vertices = load_mesh(mesh, recenter=False).vertices
    except MeshFileError as exc:
        return PoseScores.unavailable(samples, f"its mesh cannot be read ({exc})")
    return pose_scores(trajectory, gt, object_model(vertices, max_points), t_start_us, t_end_us,
                       workers)
