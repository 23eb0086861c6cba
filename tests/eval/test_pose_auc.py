"""ADD / ADD-S AUC and the 5 cm / 5° share of a trajectory, against brute-force computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from evtrack.eval.pose_auc import (
    AUC_FRACTION,
    PoseScores,
    auc_percent,
    estimates_at,
    object_model,
    pose_scores,
    sequence_pose_scores,
    within_percent,
)
from evtrack.sequence import GroundTruth
from evtrack.tracking.trajectory import STATUS_LOST, STATUS_TRACKING, STATUS_WAITING, Trajectory

# a 10 x 6 x 4 cm box centred on its frame: its corners and its edge midpoints
BOX = np.array([[x, y, z] for x in (-0.05, 0.0, 0.05) for y in (-0.03, 0.03)
                for z in (-0.02, 0.02)])
BOX_DIAMETER = math.sqrt(0.1 ** 2 + 0.06 ** 2 + 0.04 ** 2)


def cylinder(sides: int = 24, radius: float = 0.03, height: float = 0.1) -> np.ndarray:
    """Points on rings of a cylinder about z: ``sides`` evenly spaced per ring."""
    a = 2 * np.pi * np.arange(sides) / sides
    rings = [np.stack([radius * np.cos(a), radius * np.sin(a), np.full(sides, z)], 1)
             for z in np.linspace(-height / 2, height / 2, 5)]
    return np.concatenate(rings)


def true_poses(n: int, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) object-to-camera poses ~0.6 m in front of the camera."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(n, 3))).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3)) * 0.05 + [0.0, 0.0, 0.6]
    return T


def ground_truth(poses: np.ndarray, step_us: int = 2000) -> GroundTruth:
    """Ground truth at 0, step_us, 2 step_us, ... µs."""
    t = np.arange(len(poses), dtype=np.int64) * step_us
    return GroundTruth(t, poses, t, np.zeros((len(poses), 6)))


def trajectory(t_us, poses, status=None) -> Trajectory:
    n = len(t_us)
    status = np.full(n, STATUS_TRACKING) if status is None else status
    return Trajectory(torch.as_tensor(t_us), torch.as_tensor(poses), torch.zeros(n, 6),
                      torch.as_tensor(status, dtype=torch.int8))


def brute_force_auc(errors: np.ndarray, tau: float, steps: int = 100_001) -> float:
    """Area under ``τ ↦ share of errors below τ`` on a fine grid of [0, tau], in %."""
    grid = np.linspace(0.0, tau, steps)
    e = np.where(np.isfinite(errors), errors, np.inf)
    accuracy = (e[None, :] < grid[:, None]).mean(axis=1)
    return float(100 * np.trapezoid(accuracy, grid) / tau)


def test_auc_equals_a_fine_threshold_sweep():
    rng = np.random.default_rng(0)
    tau = 0.02
    errors = np.concatenate([rng.uniform(0, 0.03, 300), [0.0, tau, np.inf, np.nan]])
    assert auc_percent(errors, tau) == pytest.approx(brute_force_auc(errors, tau), abs=2e-3)
    # all perfect, all failed, none
    assert auc_percent(np.zeros(5), tau) == 100.0
    assert auc_percent(np.full(5, np.inf), tau) == 0.0
    assert math.isnan(auc_percent(np.zeros(0), tau))
    with pytest.raises(ValueError):
        auc_percent(errors, 0.0)


def test_within_share_against_a_direct_count():
    rng = np.random.default_rng(1)
    p = rng.uniform(0, 0.1, 500)
    r = rng.uniform(0, 10, 500)
    p[:3], r[:3] = np.inf, np.nan  # failures
    direct = sum(1 for a, b in zip(p, r, strict=True) if a < 0.05 and b < 5.0) / 500
    assert within_percent(p, r) == pytest.approx(100 * direct)
    assert within_percent([0.049, 0.05, 0.01], [1.0, 1.0, 5.0]) == pytest.approx(100 / 3)


def test_translation_offset_gives_add_equal_to_the_offset():
    T = true_poses(50)
    gt = ground_truth(T)
    model = object_model(BOX)
    tau = AUC_FRACTION * BOX_DIAMETER
    for d in (0.004, 0.25 * tau, tau, 2 * tau):
        est = T.copy()
        est[:, :3, 3] += d * np.array([0.6, 0.0, 0.8])
        scores = pose_scores(trajectory(gt.pose_t_us, est), gt, model)
        assert scores.diameter_m == pytest.approx(BOX_DIAMETER)
        assert scores.add_auc == pytest.approx(100 * max(0.0, 1 - d / tau), abs=1e-9)
        assert scores.samples == scores.tracked == 50
        assert scores.within_5cm_5deg == 100.0  # a few mm, no rotation
    from evtrack.eval.pose_metrics import add_distances

    est = T.copy()
    est[:, :3, 3] += [0.0, 0.003, 0.0]
    np.testing.assert_allclose(add_distances(est, T, BOX), 0.003, rtol=1e-9)


@pytest.mark.parametrize("points, turn", [
    (BOX, Rotation.from_euler("z", 180, degrees=True)),      # a box about its axis, 180°
    (cylinder(), Rotation.from_euler("z", 3 * 15, degrees=True)),  # a cylinder, 3 of 24 sides
])
def test_adds_forgives_a_symmetry_that_add_does_not(points, turn):
    T = true_poses(20, seed=2)
    sym = np.eye(4)
    sym[:3, :3] = turn.as_matrix()
    est = T @ sym  # the object turned about its own symmetry axis
    gt = ground_truth(T)
    scores = pose_scores(trajectory(gt.pose_t_us, est), gt, object_model(points))
    assert scores.adds_auc == pytest.approx(100.0, abs=1e-6)
    assert scores.add_auc < 50.0


def test_untracked_samples_count_as_failures():
    """GT at 2 ms, trajectory at 1 ms from 1 ms: the GT sample at 0 has no estimate yet; a
    waiting stretch, a lost stretch and a NaN pose fail; the rest are perfect."""
    n_gt = 101
    T = true_poses(n_gt, seed=3)
    gt = ground_truth(T)
    t_traj = np.arange(1, 201, dtype=np.int64) * 1000
    poses = np.stack([gt.pose_at(torch.tensor(int(t))).numpy() for t in t_traj])
    status = np.full(len(t_traj), STATUS_TRACKING)
    status[:40] = STATUS_WAITING   # t <= 40 ms
    status[120:150] = STATUS_LOST  # 121..150 ms
    poses[171] = np.nan            # 172 ms
    traj = trajectory(t_traj, poses, status)
    index, has = estimates_at(traj, gt.pose_t_us)
    expected = np.zeros(n_gt, bool)
    for i, t in enumerate(gt.pose_t_us.numpy()):
        k = np.searchsorted(t_traj, t, side="right") - 1  # the latest sample at or before t
        expected[i] = (k >= 0 and status[k] == STATUS_TRACKING
                       and np.isfinite(poses[k]).all())
    assert np.array_equal(has.numpy(), expected)
    # 0 ms (no output yet), 2-40 ms (waiting), 122-150 ms (lost), 172 ms (NaN) fail
    assert not expected[0] and expected.sum() == 101 - 1 - 20 - 15 - 1
    scores = pose_scores(traj, gt, object_model(BOX))
    share = 100 * expected.mean()
    assert scores.samples == n_gt and scores.tracked == expected.sum()
    assert scores.add_auc == pytest.approx(share) and scores.adds_auc == pytest.approx(share)
    assert scores.within_5cm_5deg == pytest.approx(share)
    # the span: only the GT samples in [100, 140] ms (21 of them, 10 lost)
    part = pose_scores(traj, gt, object_model(BOX), t_start_us=100_000, t_end_us=140_000)
    assert part.samples == 21 and part.add_auc == pytest.approx(100 * 11 / 21)
    # a trajectory that never tracked scores 0, not NaN
    never = pose_scores(trajectory(t_traj, poses, np.full(len(t_traj), STATUS_WAITING)), gt,
                        object_model(BOX))
    assert (never.add_auc, never.adds_auc, never.within_5cm_5deg, never.tracked) == (0, 0, 0, 0)


def test_scores_match_per_pose_brute_force():
    """Noisy estimates: AUCs from the one-pose functions, 5 cm / 5° from scipy."""
    from evtrack.eval.pose_metrics import add_distance, adds_distance

    rng = np.random.default_rng(4)
    T = true_poses(60, seed=4)
    est = T.copy()
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(
        rng.normal(size=(60, 3)) * 0.08).as_matrix()
    est[:, :3, 3] += rng.normal(size=(60, 3)) * 0.02
    gt = ground_truth(T)
    points = cylinder()
    scores = pose_scores(trajectory(gt.pose_t_us, est), gt, object_model(points))
    tau = AUC_FRACTION * scores.diameter_m
    add = np.array([add_distance(a, b, points) for a, b in zip(est, T, strict=True)])
    adds = np.array([adds_distance(a, b, points) for a, b in zip(est, T, strict=True)])
    assert 0 < scores.add_auc < 100
    assert scores.add_auc == pytest.approx(brute_force_auc(add, tau), abs=2e-3)
    assert scores.adds_auc == pytest.approx(brute_force_auc(adds, tau), abs=2e-3)
    pos = np.linalg.norm(est[:, :3, 3] - T[:, :3, 3], axis=1)
    rot = np.rad2deg(Rotation.from_matrix(
        np.einsum("nji,njk->nik", T[:, :3, :3], est[:, :3, :3])).magnitude())
    assert scores.within_5cm_5deg == pytest.approx(100 * np.mean((pos < 0.05) & (rot < 5)))


def test_model_points_are_a_deterministic_subset_and_the_diameter_uses_all_vertices():
    rng = np.random.default_rng(5)
    vertices = rng.normal(size=(10_000, 3)) * 0.05
    vertices[1] = [1.0, 0.0, 0.0]  # the two farthest points, skipped by the even pick
    vertices[2] = [-1.0, 0.0, 0.0]
    model = object_model(vertices, max_points=500)
    assert len(model.points) == 500 and len(model.vertices) == 10_000
    assert not np.isin(model.points[:, 0], [1.0, -1.0]).any()
    assert model.diameter_m == pytest.approx(2.0)
    again = object_model(vertices, max_points=500)
    assert np.array_equal(model.points, again.points)
    assert len(object_model(BOX).points) == len(BOX)
    with pytest.raises(ValueError):
        object_model(np.zeros((5, 2)))


class _Sequence:
    """What sequence_pose_scores reads of a :class:`~evtrack.Sequence`."""

    def __init__(self, mesh_file, ground_truth):
        self.mesh_file = mesh_file
        self.ground_truth = ground_truth


def test_a_sequence_without_a_mesh_gets_nan_and_a_reason(tmp_path):
    T = true_poses(10)
    gt = ground_truth(T)
    traj = trajectory(gt.pose_t_us, T)
    scores = sequence_pose_scores(traj, _Sequence(None, gt))
    assert math.isnan(scores.add_auc) and math.isnan(scores.within_5cm_5deg)
    assert scores.samples == 10 and "object.mesh" in scores.note
    scores = sequence_pose_scores(traj, _Sequence(tmp_path / "gone.glb", gt))
    assert math.isnan(scores.adds_auc) and "cannot be read" in scores.note
    assert "not computed" in str(scores)


def test_a_sequence_mesh_is_read_in_its_object_frame(tmp_path):
    """The mesh's own frame (not recentred): an offset mesh keeps its offset."""
    import trimesh

    mesh = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    mesh.apply_translation([0.2, 0.0, 0.0])
    path = tmp_path / "offset.ply"
    mesh.export(path)
    T = true_poses(10)
    gt = ground_truth(T)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("x", 180, degrees=True).as_matrix()
    # turned about the object frame's x axis: the offset box maps onto itself
    scores = sequence_pose_scores(trajectory(gt.pose_t_us, T @ turn), _Sequence(path, gt))
    assert scores.note == "" and scores.adds_auc == pytest.approx(100.0)
    # about z, it swings 40 cm away
    turn[:3, :3] = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    scores = sequence_pose_scores(trajectory(gt.pose_t_us, T @ turn), _Sequence(path, gt))
    assert scores.adds_auc == 0.0 and isinstance(scores, PoseScores)


def test_adds_searches_all_the_vertices_while_averaging_over_some():
    """A model with fewer points than vertices: ADD averages over its points; ADD-S over its
    points too, each one's nearest among all the vertices."""
    from scipy.spatial.distance import cdist

    rng = np.random.default_rng(6)
    vertices = cylinder(sides=72)
    model = object_model(vertices, max_points=40)
    assert len(model.points) == 40
    T = true_poses(8, seed=6)
    est = T.copy()
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(
        rng.normal(size=(8, 3)) * 0.05).as_matrix()
    est[:, :3, 3] += rng.normal(size=(8, 3)) * 0.005
    gt = ground_truth(T)
    scores = pose_scores(trajectory(gt.pose_t_us, est), gt, model)
    add, adds = [], []
    for E, G in zip(est, T, strict=True):
        true_pts = model.points @ G[:3, :3].T + G[:3, 3]
        add.append(np.linalg.norm(model.points @ E[:3, :3].T + E[:3, 3] - true_pts, axis=1).mean())
        adds.append(cdist(true_pts, vertices @ E[:3, :3].T + E[:3, 3]).min(axis=1).mean())
    tau = AUC_FRACTION * scores.diameter_m
    assert scores.add_auc == pytest.approx(100 * np.mean(np.clip(1 - np.array(add) / tau, 0, 1)))
    assert scores.adds_auc == pytest.approx(100 * np.mean(np.clip(1 - np.array(adds) / tau, 0,
                                                                         1)))
    assert scores.points == 40
