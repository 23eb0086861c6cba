"""Batched P3P: the poses that put three object points on three camera rays, for many
problems at once (numpy; no Python loop over problems).

OpenCV's ``cv2.solveP3P`` solves one problem per call; the pose search
(:mod:`evtrack.models.pose_search`) poses ~700 at a time, and there the per-call cost was
most of its time. This module solves them together, the classic way (Grunert's distances,
as reviewed by Haralick et al., IJCV 1994):

1. With unit rays ``f_k`` and unknown distances ``s_k`` along them, the law of cosines on
   each pair of points gives three equations ``s_i^2 + s_j^2 - 2 s_i s_j cos(f_i, f_j) =
   |P_i - P_j|^2``. With ``u = s_2 / s_1`` and ``v = s_3 / s_1``, two of them give ``u`` as
   a rational function of ``v`` and the third a quartic in ``v``; its coefficients are built
   here by polynomial arithmetic on the equations themselves (no transcribed formula).
2. The quartic's real roots come from its companion matrices' eigenvalues (batched); each
   gives ``s_1, s_2, s_3``, polished by two Gauss-Newton steps on the three equations.
   Roots that do not satisfy them (spurious ones of the elimination, complex pairs) or put a
   point behind the camera are dropped.
3. The rotation takes the object triangle's orthonormal frame onto that of the camera
   points ``s_k f_k``; the translation matches their centroids.

Pinned by ``tests/models/test_p3p.py`` against ground truth and against ``cv2.solveP3P``.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["bearings", "solve_p3p"]

_RESIDUAL_TOLERANCE = 1e-6
"""A solution's largest law-of-cosines residual, relative to the largest squared side."""


def bearings(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """(..., 2) pixels -> (..., 3) unit rays in the camera frame (lens distortion removed
    with ``cv2.undistortPoints`` when ``dist`` has a non-zero coefficient)."""
    pixels = np.asarray(pixels, np.float64)
    flat = pixels.reshape(-1, 2)
    if dist is not None and np.any(dist):
        xy = cv2.undistortPoints(flat[:, None, :], np.asarray(K, np.float64),
                                 np.asarray(dist, np.float64)).reshape(-1, 2)
    else:
        K = np.asarray(K, np.float64)
        y = (flat[:, 1] - K[1, 2]) / K[1, 1]
        x = (flat[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        xy = np.stack([x, y], axis=1)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return rays.reshape(pixels.shape[:-1] + (3,))


def _polymul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Batched polynomial product: (N, m) x (N, n) coefficients, lowest degree first."""
    out = np.zeros((p.shape[0], p.shape[1] + q.shape[1] - 1))
    for i in range(p.shape[1]):
        out[:, i:i + q.shape[1]] += p[:, i:i + 1] * q
    return out


def _pad(p: np.ndarray, n: int) -> np.ndarray:
    return np.pad(p, ((0, 0), (0, n - p.shape[1])))


def _frame(points: np.ndarray) -> np.ndarray:
    """(M, 3, 3) triangles (rows: points) -> (M, 3, 3) orthonormal frames (columns: the
    first edge's direction, the in-plane normal to it, the plane's normal)."""
    e1 = points[:, 1] - points[:, 0]
    normal = np.cross(e1, points[:, 2] - points[:, 0])
    e1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
    return np.stack([e1, np.cross(normal, e1), normal], axis=2)


def _quartic_roots(coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Real roots of (N, 5) quartics (lowest degree first).

    Returns:
        (M,) roots and (M,) the index of their quartic. A quartic whose leading coefficient
        vanishes (relative to its largest one) is solved at the degree it has.
    """
    scale = np.abs(coeffs).max(axis=1, keepdims=True)
    scale[scale == 0] = 1.0
    c = coeffs / scale
    roots, owners = [], []
    remaining = np.ones(len(c), dtype=bool)
    for degree in (4, 3, 2, 1):
        take = remaining & (np.abs(c[:, degree]) > 1e-12)
        remaining &= ~take
        if not take.any():
            continue
        monic = c[take, :degree] / c[take, degree:degree + 1]
        companion = np.zeros((int(take.sum()), degree, degree))
        companion[:, 0, :] = -monic[:, ::-1]
        if degree > 1:
            companion[:, np.arange(1, degree), np.arange(degree - 1)] = 1.0
        eig = np.linalg.eigvals(companion)  # (n, degree)
        # a double root splits into a complex pair under round-off: keep near-real ones,
        # the Gauss-Newton polish and the residual test sort them out
        real = np.abs(eig.imag) <= 1e-6 * (1.0 + np.abs(eig.real))
        idx = np.nonzero(take)[0]
        r, k = np.nonzero(real)
        roots.append(eig.real[r, k])
        owners.append(idx[r])
    if not roots:
        return np.zeros(0), np.zeros(0, dtype=np.int64)
    return np.concatenate(roots), np.concatenate(owners)


def solve_p3p(object_points: np.ndarray, rays: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pose ``x_cam = R x_obj + t`` that puts each of three object points on its ray.

    Args:
        object_points: (N, 3, 3) three object points per problem (metres; not collinear).
        rays: (N, 3, 3) their unit rays in the camera frame (:func:`bearings`).

    Returns:
        ``R`` (M, 3, 3), ``t`` (M, 3) and ``problem`` (M,) the index of each solution's
        problem; up to four solutions per problem, none for a degenerate one. Every solution
        has its three points in front of the camera.
    """
    P = np.asarray(object_points, np.float64)
    f = np.asarray(rays, np.float64)
    n = len(P)
    if n == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    # sides: a opposite point 0 (|P1 - P2|), b opposite point 1, c opposite point 2
    a2 = np.sum((P[:, 1] - P[:, 2]) ** 2, axis=1)
    b2 = np.sum((P[:, 0] - P[:, 2]) ** 2, axis=1)
    c2 = np.sum((P[:, 0] - P[:, 1]) ** 2, axis=1)
    ca = np.sum(f[:, 1] * f[:, 2], axis=1)  # cos between rays 1 and 2
    cb = np.sum(f[:, 0] * f[:, 2], axis=1)
    cg = np.sum(f[:, 0] * f[:, 1], axis=1)
    ok = b2 > 0
    b2s = np.where(ok, b2, 1.0)
    # with u = s1/s0, v = s2/s0:
    #   (A) b2 (u^2 + v^2 - 2 u v ca) = a2 (1 + v^2 - 2 v cb)
    #   (B) b2 (1 + u^2 - 2 u cg)     = c2 (1 + v^2 - 2 v cb)
    # (A) - (B) is linear in u: u = N(v) / D(v)
    ones, zeros = np.ones(n), np.zeros(n)
    w = np.stack([ones, -2 * cb, ones], axis=1)  # 1 - 2 v cb + v^2
    k = (c2 - a2) / b2s
    numer = k[:, None] * w + np.stack([-ones, zeros, ones], axis=1)  # N(v)
    denom = np.stack([-2 * cg, 2 * ca], axis=1)  # D(v) = 2 (v ca - cg)
    # (B) times D^2: b2 (D^2 + N^2 - 2 cg N D) - c2 w D^2 = 0, a quartic in v
    d2 = _polymul(denom, denom)
    quartic = b2s[:, None] * (_pad(d2, 5) + _polymul(numer, numer)
                              - 2 * cg[:, None] * _pad(_polymul(numer, denom), 5))
    quartic -= c2[:, None] * _polymul(w, d2)
    v, owner = _quartic_roots(np.where(ok[:, None], quartic, 0.0))
    keep = ok[owner]
    v, owner = v[keep], owner[keep]
    num_v = numer[owner, 0] + numer[owner, 1] * v + numer[owner, 2] * v * v
    den_v = denom[owner, 0] + denom[owner, 1] * v
    with np.errstate(divide="ignore", invalid="ignore"):
        u = num_v / den_v
        s0 = np.sqrt(b2[owner] / (1 + v * v - 2 * v * cb[owner]))
    s = np.stack([s0, u * s0, v * s0], axis=1)  # (M, 3) distances along the rays
    good = np.all(np.isfinite(s), axis=1)
    s, owner = s[good], owner[good]
    sides = np.stack([a2, b2, c2], axis=1)[owner]  # pairs (1,2), (0,2), (0,1)
    cosines = np.stack([ca, cb, cg], axis=1)[owner]
    pairs = ((1, 2), (0, 2), (0, 1))

    def residual(s: np.ndarray) -> np.ndarray:
        return np.stack([s[:, i] ** 2 + s[:, j] ** 2 - 2 * s[:, i] * s[:, j] * cosines[:, r]
                         - sides[:, r] for r, (i, j) in enumerate(pairs)], axis=1)

    for _ in range(2):  # Gauss-Newton polish
        jac = np.zeros((len(s), 3, 3))
        for r, (i, j) in enumerate(pairs):
            jac[:, r, i] = 2 * s[:, i] - 2 * s[:, j] * cosines[:, r]
            jac[:, r, j] = 2 * s[:, j] - 2 * s[:, i] * cosines[:, r]
        solvable = np.abs(np.linalg.det(jac)) > 1e-12 * np.max(sides, axis=1) ** 1.5
        if solvable.any():
            step = np.linalg.solve(jac[solvable], residual(s[solvable])[..., None])[..., 0]
            s[solvable] -= step
    err = np.abs(residual(s)).max(axis=1) / np.max(sides, axis=1)
    good = (err <= _RESIDUAL_TOLERANCE) & np.all(s > 0, axis=1)
    s, owner = s[good], owner[good]
    if len(s) == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    cam = s[..., None] * f[owner]  # (M, 3, 3) points in the camera frame
    obj = P[owner]
    # the triangles are congruent (to the polish's accuracy): the rotation takes the object
    # triangle's orthonormal frame onto the camera triangle's
    R = _frame(cam) @ _frame(obj).transpose(0, 2, 1)
    t = cam.mean(axis=1) - np.einsum("mij,mj->mi", R, obj.mean(axis=1))
    return R, t, owner
