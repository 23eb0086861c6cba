"""ADD / ADD-S against brute-force computations."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from evtrack.eval.pose_metrics import (
    add_distance,
    add_distances,
    adds_distance,
    adds_distances,
    object_diameter,
    pooled_rate_interval,
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


def test_batched_add_and_adds_match_the_one_pose_functions():
    """More poses than one chunk (256), so the chunks are joined too."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.05, 0.05, (40, 3))
    A = np.stack([random_pose(rng) for _ in range(300)])
    B = np.stack([random_pose(rng, 0.1) for _ in range(300)])
    np.testing.assert_allclose(add_distances(A, B, pts),
                               [add_distance(a, b, pts) for a, b in zip(A, B, strict=True)],
                               rtol=1e-12)
    np.testing.assert_allclose(adds_distances(A, B, pts, workers=2),
                               [adds_distance(a, b, pts) for a, b in zip(A, B, strict=True)],
                               rtol=1e-9, atol=1e-15)
    assert add_distances(A[:0], B[:0], pts).shape == (0,)


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


def test_diameter_of_a_large_hull_matches_all_pairs():
    """Every point on the hull (a sphere), more of them than one chunk of rows."""
    from scipy.spatial.distance import pdist

    rng = np.random.default_rng(4)
    pts = rng.normal(size=(700, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    assert object_diameter(pts) == pytest.approx(pdist(pts).max())


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
    # 10 cm off is not a gross miss (> 10 cm): none of the three detections is
    assert acc.gross_miss_rate == 0.0 and acc.gross_miss_m == 0.10
    farther = truths[2].copy()
    farther[:3, 3] += [0.0, 0.0, 0.1001]
    acc = pose_accuracy([truths[0], near, farther, None], truths, pts)
    assert acc.gross_miss_rate == pytest.approx(1 / 3)  # of the detected frames
    assert pose_accuracy([near, None, None, None], truths[:1] * 4, pts,
                         gross_miss_m=0.004).gross_miss_rate == 1.0
    assert np.isnan(pose_accuracy([None], truths[:1], pts).gross_miss_rate)
    with pytest.raises(ValueError):
        pose_accuracy([None], truths, pts)


def _exact_bootstrap_quantile(passed, frames, p):
    """The p-quantile (smallest atom with CDF >= p) of the pooled rate over all S^S equally
    likely resamples of S sequences, by enumeration."""
    atoms = sorted(sum(passed[i] for i in d) / sum(frames[i] for i in d)
                   for d in itertools.product(range(len(frames)), repeat=len(frames)))
    return atoms[int(np.ceil(p * len(atoms))) - 1]


@pytest.mark.parametrize("passed, frames, level", [
    ([0, 60], [60, 60], 0.9),        # atoms 0 (1/4), 0.5 (1/2), 1 (1/4)
    ([0, 60], [60, 60], 0.4),        # both quantiles inside the 0.5 atom
    ([60, 0, 15], [60, 60, 30], 0.5),
])
def test_pooled_rate_interval_matches_the_enumerated_bootstrap(passed, frames, level):
    low, high = pooled_rate_interval(np.array(passed), np.array(frames), level=level,
                                     resamples=20000)
    atoms = {sum(passed[i] for i in d) / sum(frames[i] for i in d)
             for d in itertools.product(range(len(frames)), repeat=len(frames))}
    # the quantiles fall on atoms away from the CDF's jumps for these cases
    for value, p in ((low, (1 - level) / 2), (high, (1 + level) / 2)):
        assert min(abs(value - a) for a in atoms) < 1e-9
        assert value == pytest.approx(_exact_bootstrap_quantile(passed, frames, p))


def test_pooled_rate_interval_resamples_sequences_not_frames():
    # six sequences, half passing every frame, half none: the pooled rate is 0.5, and
    # resampling sequences leaves it wide; resampling 360 independent frames would give ~0.46-0.54
    passed, frames = np.array([60, 0, 60, 0, 60, 0]), np.full(6, 60)
    low, high = pooled_rate_interval(passed, frames)
    assert low <= 0.2 and high >= 0.8
    # identical sequences: no spread
    assert pooled_rate_interval(np.full(4, 30), np.full(4, 60)) == (0.5, 0.5)
    # reproducible
    assert pooled_rate_interval(passed, frames, seed=3) == pooled_rate_interval(passed, frames,
                                                                                seed=3)


@pytest.mark.parametrize("passed, frames, kwargs", [
    ([1, 2], [3], {}), ([], [], {}), ([4], [3], {}), ([1], [0], {}), ([1], [3], {"level": 1.0}),
    ([1], [3], {"resamples": 0}),
])
def test_pooled_rate_interval_rejects_bad_input(passed, frames, kwargs):
    with pytest.raises(ValueError):
        pooled_rate_interval(np.array(passed), np.array(frames), **kwargs)
