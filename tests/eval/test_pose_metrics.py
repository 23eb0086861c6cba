"""ADD / ADD-S against brute-force computations."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from evtrack.eval.pose_metrics import (
    add_distance,
    adds_distance,
    object_diameter,
    pose_accuracy,
)


def random_pose(rng: np.random.Generator, angle_scale: float = 1.0) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * angle_scale).as_matrix()
    T[:3, 3] = rng.normal(size=3) * 0.1 + [0, 0, 0.8]
    return T


def test_add_and_adds_match_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.05, 0.05, (60, 3))
    for _ in range(5):
        A, B = random_pose(rng), random_pose(rng)
        pa = pts @ A[:3, :3].T + A[:3, 3]
        pb = pts @ B[:3, :3].T + B[:3, 3]
        assert add_distance(A, B, pts) == pytest.approx(np.mean(np.linalg.norm(pa - pb, axis=1)))
        brute = np.mean([min(np.linalg.norm(q - p) for p in pa) for q in pb])
        assert adds_distance(A, B, pts) == pytest.approx(brute)


def test_adds_is_zero_under_a_symmetry():
    # a square's corners: rotating by 90 degrees about z maps the set onto itself
    pts = np.array([[1, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]], float) * 0.05
    T_true = np.eye(4)
    T_est = np.eye(4)
    T_est[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    assert adds_distance(T_est, T_true, pts) == pytest.approx(0.0, abs=1e-12)
    assert add_distance(T_est, T_true, pts) > 0.05


def test_diameter_matches_all_pairs():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(200, 3))
    brute = max(np.linalg.norm(a - b) for a, b in itertools.combinations(pts, 2))
    assert object_diameter(pts) == pytest.approx(brute)


def test_pose_accuracy_counts_missed_detections_as_failures():
    rng = np.random.default_rng(2)
    pts = rng.uniform(-0.05, 0.05, (50, 3))
    truths = [random_pose(rng) for _ in range(4)]
    near = truths[1].copy()
    near[:3, 3] += [0.003, 0.0, 0.004]  # 5 mm off
    far = truths[2].copy()
    far[:3, 3] += [0.1, 0.0, 0.0]
    acc = pose_accuracy([truths[0], near, far, None], truths, pts)
    assert acc.frames == 4 and acc.detected == 3 and acc.detection_rate == 0.75
    assert acc.median_translation_cm == pytest.approx(0.5)
    assert acc.add_pass == 0.5 and acc.adds_pass == 0.5
    with pytest.raises(ValueError):
        pose_accuracy([None], truths, pts)
