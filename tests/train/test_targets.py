"""Belief / affinity targets against a brute-force per-cell reference, and a decode round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evtrack.models import Cuboid, extract_instances
from evtrack.train import TargetConfig, make_targets


def brute_force(keypoints, size, stride, sigma, radius):
    h, w = size[0] // stride, size[1] // stride
    belief = np.zeros((9, h, w))
    aff_sum = np.zeros((8, 2, h, w))
    count = np.zeros((8, h, w))
    for i in range(h):
        for j in range(w):
            # centre of the stride x stride block of pixels this cell covers
            cx = np.mean(np.arange(j * stride, (j + 1) * stride))
            cy = np.mean(np.arange(i * stride, (i + 1) * stride))
            for inst in keypoints:
                for k in range(9):
                    u, v = inst[k]
                    if math.isnan(u):
                        continue
                    d2 = (cx - u) ** 2 + (cy - v) ** 2
                    belief[k, i, j] = max(belief[k, i, j], math.exp(-d2 / (2 * sigma**2)))
                    if k < 8 and not math.isnan(inst[8, 0]) and d2 <= radius**2:
                        vec = inst[8] - inst[k]
                        aff_sum[k, :, i, j] += vec / np.linalg.norm(vec)
                        count[k, i, j] += 1
    aff = np.where(count[:, None] > 0, aff_sum / np.maximum(count[:, None], 1), 0.0)
    return belief, aff.reshape(16, h, w)


def test_matches_brute_force_with_overlap_and_missing_points():
    rng = np.random.default_rng(0)
    kp = rng.uniform(0, 64, (2, 9, 2))
    kp[1, :, 0] = kp[0, :, 0] + rng.normal(0, 3, 9)  # overlapping discs: averaged vectors
    kp[1, :, 1] = kp[0, :, 1] + rng.normal(0, 3, 9)
    kp[0, 3] = np.nan  # a missing corner
    kp[1, 8] = np.nan  # an instance without centroid: beliefs, no affinities
    cfg = TargetConfig(stride=8, sigma_px=5.0, affinity_radius_px=10.0)
    belief, affinity = make_targets(kp, (48, 64), cfg)
    ref_b, ref_a = brute_force(kp, (48, 64), 8, 5.0, 10.0)
    assert belief.shape == (9, 6, 8) and affinity.shape == (16, 6, 8)
    np.testing.assert_allclose(belief, ref_b, atol=1e-6)
    np.testing.assert_allclose(affinity, ref_a, atol=1e-6)
    assert affinity.any()


def test_no_instances_gives_zero_maps():
    belief, affinity = make_targets(np.zeros((0, 9, 2)), (32, 48))
    assert belief.shape == (9, 4, 6) and not belief.any() and not affinity.any()


def test_size_must_be_a_multiple_of_the_stride():
    with pytest.raises(ValueError, match="multiple of stride 8"):
        make_targets(np.zeros((0, 9, 2)), (30, 48))


def test_targets_decode_back_to_the_keypoints():
    kp = np.array([Cuboid((0.1, 0.1, 0.1)).points()[:, :2] * 300 + (120, 90)])
    belief, affinity = make_targets(kp, (192, 256))
    (inst,) = extract_instances(belief, affinity, stride=8)
    np.testing.assert_allclose(inst.keypoints, kp[0], atol=0.05)
