"""Position and rotation errors against brute-force computations."""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from evtrack.eval.metrics import position_errors, rotation_errors, tracking_errors
from evtrack.tracking.trajectory import Trajectory


def _poses(n: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return torch.from_numpy(T)


def test_errors_match_brute_force() -> None:
    A, B = _poses(200, 0), _poses(200, 1)
    # near-identical and near-opposite rotations, where arccos of the trace is inaccurate
    B[:5] = A[:5]
    B[5, :3, :3] = A[5, :3, :3] @ torch.from_numpy(Rotation.from_rotvec([1e-7, 0, 0]).as_matrix())
    B[6, :3, :3] = A[6, :3, :3] @ torch.from_numpy(
        Rotation.from_rotvec([0, math.pi - 1e-6, 0]).as_matrix())
    p, r = position_errors(A, B).numpy(), rotation_errors(A, B).numpy()
    for i in range(len(A)):
        a, b = A[i].numpy(), B[i].numpy()
        assert abs(p[i] - math.dist(a[:3, 3], b[:3, 3])) < 1e-12
        rel = Rotation.from_matrix(b[:3, :3].T @ a[:3, :3])
        assert abs(r[i] - np.linalg.norm(rel.as_rotvec())) < 1e-9
    assert abs(r[5] - 1e-7) < 1e-12 and abs(r[6] - (math.pi - 1e-6)) < 1e-9


def test_tracking_errors_rmse_and_sigma() -> None:
    gt_T = _poses(100, 2)
    est = gt_T.clone()
    shift = torch.linspace(0.0, 0.05, 100, dtype=torch.float64)
    est[:, 0, 3] += shift
    angle = torch.linspace(0.0, 0.2, 100, dtype=torch.float64)
    for i in range(100):
        est[i, :3, :3] = gt_T[i, :3, :3] @ torch.from_numpy(
            Rotation.from_rotvec([0, 0, float(angle[i])]).as_matrix())
    status = torch.ones(100, dtype=torch.int8)
    status[:10] = 0  # waiting: excluded
    t = torch.arange(100) * 1000

    class GT:
        @staticmethod
        def pose_at(times):
            return gt_T[(times // 1000).long()]

    err = tracking_errors(Trajectory(t, est, torch.zeros(100, 6), status), GT)
    cm = shift[10:].numpy() * 100
    deg = np.degrees(angle[10:].numpy())
    assert err.samples == 90 and err.total == 100
    assert abs(err.position_rmse_cm - np.sqrt(np.mean(cm ** 2))) < 1e-9
    assert abs(err.position_std_cm - np.std(cm)) < 1e-9
    assert abs(err.rotation_rmse_deg - np.sqrt(np.mean(deg ** 2))) < 1e-6
    assert abs(err.rotation_std_deg - np.std(deg)) < 1e-6
    window = tracking_errors(Trajectory(t, est, torch.zeros(100, 6), status), GT,
                             t_start_us=50_000)
    assert window.samples == 50
