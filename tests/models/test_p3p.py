"""Batched P3P (``evtrack.models.p3p``): simulated ground truth and OpenCV's solver as the
references, and the pose search built on it against a search built on ``cv2.solveP3P``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from pose_search_reference import opencv_search
from scipy.spatial.transform import Rotation

from evtrack.models.cuboid import CENTROID_INDEX, Cuboid
from evtrack.models.p3p import bearings, solve_p3p
from evtrack.models.pose_search import search_pose

K = np.array([[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]])


def random_problems(n: int, seed: int):
    """Three random object points per problem, a random pose, their pixels (no lens)."""
    rng = np.random.default_rng(seed)
    obj = rng.uniform(-0.1, 0.1, (n, 3, 3))
    R = Rotation.random(n, random_state=seed).as_matrix()
    t = np.stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n),
                  rng.uniform(0.3, 1.0, n)], axis=1)
    cam = np.einsum("nij,nkj->nki", R, obj) + t[:, None]
    uv = cam[..., :2] / cam[..., 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    return obj, R, t, uv


def test_bearings_are_unit_rays_through_the_pixels():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 640, (50, 2))
    rays = bearings(pts, K)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)
    back = (rays / rays[:, 2:]) @ K.T
    np.testing.assert_allclose(back[:, :2], pts, atol=1e-9)
    # with a lens: the same rays as OpenCV's undistortion
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    rays_d = bearings(pts, K, dist)
    xy = cv2.undistortPoints(pts[:, None], K, dist).reshape(-1, 2)
    np.testing.assert_allclose(rays_d[:, :2] / rays_d[:, 2:], xy, atol=1e-12)


def test_every_true_pose_is_among_the_solutions_and_every_solution_fits():
    obj, R, t, uv = random_problems(500, seed=1)
    Rs, ts, owner = solve_p3p(obj, bearings(uv, K))
    assert len(Rs) >= 500 and np.all(np.bincount(owner, minlength=500) <= 4)
    err = np.abs(Rs - R[owner]).max(axis=(1, 2)) + np.abs(ts - t[owner]).max(axis=1)
    found = np.zeros(500, dtype=bool)
    found[owner[err < 1e-7]] = True
    assert found.all()
    # each solution is a rotation that puts all three points on their pixels, in front
    eye = np.broadcast_to(np.eye(3), Rs.shape)
    np.testing.assert_allclose(np.einsum("mji,mjk->mik", Rs, Rs), eye, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(Rs), 1.0, atol=1e-9)
    cam = np.einsum("mij,mkj->mki", Rs, obj[owner]) + ts[:, None]
    assert np.all(cam[..., 2] > 0)
    proj = cam[..., :2] / cam[..., 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    np.testing.assert_allclose(proj, uv[owner], atol=1e-6)


def test_the_same_solutions_as_opencv():
    obj, _, _, uv = random_problems(300, seed=2)
    Rs, ts, owner = solve_p3p(obj, bearings(uv, K))
    total = 0
    for n in range(300):
        count, rvecs, tvecs = cv2.solveP3P(obj[n], uv[n], K, None, flags=cv2.SOLVEPNP_P3P)
        mine = np.nonzero(owner == n)[0]
        assert len(mine) == count
        for rvec, tvec in zip(rvecs, tvecs, strict=True):
            Rc = cv2.Rodrigues(rvec)[0]
            diff = (np.abs(Rs[mine] - Rc).max(axis=(1, 2))
                    + np.abs(ts[mine] - tvec.reshape(3)).max(axis=1))
            assert diff.min() < 1e-6
            total += 1
    assert total > 300  # many problems have more than one solution


def test_degenerate_problems_give_no_solution_and_do_not_disturb_the_others():
    obj, R, t, uv = random_problems(4, seed=3)
    obj[1] = [[0, 0, 0], [0.05, 0, 0], [0.1, 0, 0]]  # collinear object points
    obj[2] = 0.0  # three times the same point
    Rs, ts, owner = solve_p3p(obj, bearings(uv, K))
    assert set(owner.tolist()) <= {0, 3} and {0, 3} <= set(owner.tolist())
    assert np.isfinite(Rs).all() and np.isfinite(ts).all()
    empty = solve_p3p(np.zeros((0, 3, 3)), np.zeros((0, 3, 3)))
    assert [len(x) for x in empty] == [0, 0, 0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_search_finds_the_pose_opencv_p3p_finds(seed):
    # maps where every corner map fires on every corner, more weakly on the wrong ones, plus
    # one spurious peak: the pose, and its score, of a search built on cv2.solveP3P
    rng = np.random.default_rng(seed)
    cuboid = Cuboid((0.09, 0.16, 0.06))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.8).as_matrix()
    T[:3, 3] = (rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.6)
    uv = cuboid.project(T, K)
    stride, h, w = 8, 60, 80

    def to_grid(p):
        return (p - 3.5) / stride

    gy, gx = np.mgrid[0:h, 0:w]
    cx, cy = gx * stride + 3.5, gy * stride + 3.5
    belief = np.zeros((9, h, w))
    for k in range(9):
        for c in range(9):
            if (k == CENTROID_INDEX) != (c == CENTROID_INDEX):
                continue
            amp = 1.0 if k == c else 0.4
            belief[k] += amp * np.exp(-((cx - uv[c, 0]) ** 2 + (cy - uv[c, 1]) ** 2) / 2 / 5.0**2)
    spurious = uv[:8].mean(axis=0) + rng.uniform(30, 60, 2)
    points = np.concatenate([np.c_[uv[:8] + rng.normal(0, 0.3, (8, 2)), np.ones(8)],
                             [[*spurious, 0.5]]])
    found = search_pose(points, uv[CENTROID_INDEX], belief, cuboid, K, None, to_grid,
                        max_points=9)
    R_ref, t_ref, score_ref, _ = opencv_search(points, uv[CENTROID_INDEX], belief, cuboid, K,
                                               to_grid)
    assert found.score == pytest.approx(score_ref, abs=1e-9)
    np.testing.assert_allclose(cv2.Rodrigues(found.rvec)[0], R_ref, atol=1e-7)
    np.testing.assert_allclose(found.tvec.reshape(3), t_ref, atol=1e-7)
    assert np.linalg.norm(found.tvec.reshape(3) - T[:3, 3]) < 0.01
    assert found.hypotheses > 9 * 8 // 2 * 24  # about two solutions per problem


def test_the_searchs_projection_with_a_lens_equals_opencv_pose_by_pose():
    from evtrack.models.pose_search import _project

    rng = np.random.default_rng(5)
    obj = rng.uniform(-0.1, 0.1, (9, 3))
    R = Rotation.random(6, random_state=5).as_matrix()
    t = np.c_[rng.uniform(-0.1, 0.1, (6, 2)), rng.uniform(0.4, 1.0, 6)]
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    uv, z = _project(obj, R, t, K, dist)
    for n in range(6):
        ref = cv2.projectPoints(obj, cv2.Rodrigues(R[n])[0], t[n], K, dist)[0].reshape(-1, 2)
        np.testing.assert_allclose(uv[n], ref, atol=1e-9)
        np.testing.assert_allclose(z[n], (obj @ R[n].T + t[n])[:, 2])
