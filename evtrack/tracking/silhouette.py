"""The object's predicted silhouette in the event camera: which events belong to the object.

The tracker keeps only the events near the object's predicted image. The image of the object
is approximated by the convex hull of its projected mesh: the mesh's 3-D convex hull vertices
(tens to a few hundred points, computed once with trimesh) are projected with the camera and
their 2-D convex hull taken with OpenCV. This is a superset of the true silhouette (equal for
convex objects), costs tens of microseconds per pose, needs no OpenGL, and is exactly what an
event mask needs: events within ``margin`` pixels of it are kept (the test is the polygon's
half-planes moved outwards by ``margin``, a mitred offset, slightly generous at sharp corners).

The hull also gives the depth range of the object at the predicted pose, which the depth
lookup uses to reject background and occluder pixels (:mod:`evtrack.tracking.depth_sources`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.filters.scalar_lie import rotation_matrix
from evtrack.runtime.jit import available as jit_available
from evtrack.runtime.jit import njit

__all__ = ["Silhouette", "SilhouettePolygon", "hull_vertices", "pixels_in_polygon",
           "points_in_polygon"]

MIN_DEPTH_M = 1e-3
"""Hull vertices closer than this to the camera plane make the projection meaningless: the
pose then has no silhouette (the object is behind or at the camera)."""


def hull_vertices(vertices: np.ndarray) -> np.ndarray:
    """The vertices of the 3-D convex hull of a point set (trimesh/qhull).

    Args:
        vertices: (V, 3) object-frame points, metres.

    Returns:
        (K, 3) float64, K <= V.
    """
    import trimesh

    pts = np.asarray(vertices, np.float64).reshape(-1, 3)
    if len(pts) < 4 or not np.isfinite(pts).all():
        raise ConfigError(f"the object mesh needs at least 4 finite vertices, got {len(pts)}")
    try:
        hull = trimesh.convex.convex_hull(pts)
        return np.asarray(hull.vertices, np.float64)
    except Exception:  # flat or degenerate point sets: keep every point (still a superset)
        return pts


@dataclass
class SilhouettePolygon:
    """A projected silhouette.

    Attributes:
        vertices: (P, 2) float64 convex polygon in pixels (either orientation).
        z_range: ``(z_min, z_max)`` metres, the depth range of the hull at the pose.
        visible_fraction: share of the polygon's area inside the image, in [0, 1].
    """

    vertices: np.ndarray
    z_range: tuple[float, float]
    visible_fraction: float

    def contains(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N, 2) pixels -> (N,) bool: within ``margin`` px of the polygon."""
        return points_in_polygon(self.vertices, xy, margin)

    def contains_pixels(self, x: np.ndarray, y: np.ndarray, margin: float,
                        size: tuple[int, int]) -> np.ndarray:
        """:meth:`contains` for integer pixels of an image of ``size`` (W, H), by row spans
        (:func:`pixels_in_polygon`): the same answer, in O(N) instead of O(N x edges)."""
        return pixels_in_polygon(self.vertices, x, y, margin, size)


def _half_planes(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit outward normals (K, 2) and offsets (K,) of a convex polygon's edges (P >= 3):
    a point ``p`` is inside when ``n_k . p - o_k <= 0`` for every edge."""
    edges = np.roll(poly, -1, axis=0) - poly
    nxt = np.roll(poly, -1, axis=0)
    area2 = float(np.sum(poly[:, 0] * nxt[:, 1] - nxt[:, 0] * poly[:, 1]))
    normals = np.stack([edges[:, 1], -edges[:, 0]], 1) * (1.0 if area2 > 0 else -1.0)
    length = np.linalg.norm(normals, axis=1)
    keep = length > 0
    normals = normals[keep] / length[keep, None]
    offsets = normals[:, 0] * poly[keep, 0] + normals[:, 1] * poly[keep, 1]
    return normals, offsets


def _edge_distances(normals: np.ndarray, offsets: np.ndarray, px: np.ndarray,
                    py: np.ndarray) -> np.ndarray:
    """(M, K) signed distances of points outside the edges' lines,
    ``(px * nx_k + py * ny_k) - o_k`` in float64, element by element: the one definition both
    polygon tests use, so that they agree to the last bit (a BLAS product could round
    differently, and it would start BLAS threads)."""
    d = px[:, None] * normals[None, :, 0] + py[:, None] * normals[None, :, 1]
    return d - offsets[None, :]


def _outside_distance(normals: np.ndarray, offsets: np.ndarray, px: np.ndarray,
                      py: np.ndarray) -> np.ndarray:
    """(M,) the largest of :func:`_edge_distances`."""
    return _edge_distances(normals, offsets, px, py).max(axis=1)


def points_in_polygon(polygon: np.ndarray, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Points within ``margin`` of a convex polygon (half-plane test).

    Args:
        polygon: (P, 2) convex polygon, either orientation, P >= 1.
        xy: (N, 2) points.
        margin: pixels; the polygon's edges are moved outwards by it.

    Returns:
        (N,) bool.
    """
    poly = np.asarray(polygon, np.float64).reshape(-1, 2)
    pts = np.asarray(xy, np.float64).reshape(-1, 2)
    if len(poly) < 3:  # a point or a segment: distance to its vertices' bounding box
        lo, hi = poly.min(0) - margin, poly.max(0) + margin
        return ((pts >= lo) & (pts <= hi)).all(1)
    normals, offsets = _half_planes(poly)
    if not len(pts):
        return np.zeros(0, bool)
    return _outside_distance(normals, offsets, pts[:, 0], pts[:, 1]) <= margin


_ROUNDING = 16 * np.finfo(np.float64).eps
"""A bound on the relative rounding of an edge's distance and of its span's end (a few
operations, each off by half an ulp)."""


def pixels_in_polygon(polygon: np.ndarray, x: np.ndarray, y: np.ndarray, margin: float,
                      size: tuple[int, int]) -> np.ndarray:
    """:func:`points_in_polygon` for integer pixels, in O(H x edges + N).

    For each image row the polygon grown by ``margin`` covers one span of columns (it is
    convex, and each edge's test is monotone in x, rounding included). The spans come from
    the edges' lines, to within a pixel; a pixel more than 2 columns inside its row's span is
    in, more than 2 outside is out, and the few in between are decided by the exact test of
    :func:`points_in_polygon`. The answer is therefore that of :func:`points_in_polygon` on the
    same pixels, bit for bit.

    Args:
        polygon: (P, 2) convex polygon, either orientation.
        x, y: (N,) integer pixel coordinates inside the image.
        margin: pixels.
        size: image (W, H).

    Returns:
        (N,) bool.
    """
    poly = np.asarray(polygon, np.float64).reshape(-1, 2)
    x = np.asarray(x).reshape(-1)
    y = np.asarray(y).reshape(-1)
    if len(poly) < 3 or not len(x):
        return points_in_polygon(poly, np.stack([x, y], 1), margin)
    w, h = int(size[0]), int(size[1])
    normals, offsets = _half_planes(poly)
    nx, ny = normals[:, 0], normals[:, 1]
    rows = np.arange(h, dtype=np.float64)
    # an edge gives each row's span end to within a pixel unless |n_x| is tiny against the
    # magnitudes it is computed from; such "flat" edges are tested at the row's two ends
    scale = abs(margin) + np.abs(offsets) + w + h
    steep = np.abs(nx) > 2.0 * _ROUNDING * scale
    if jit_available():
        lo, hi = np.empty(h), np.empty(h)
        _steep_spans(nx, ny, offsets, steep, float(margin), w, h, lo, hi)
    else:
        # per row and edge: n_x * col <= margin + o - n_y * row
        rhs = (margin + offsets)[None, :] - rows[:, None] * ny[None, :]  # (H, K)
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = rhs[:, steep] / nx[steep]
        right = nx[steep] > 0
        hi = np.floor(bound[:, right]).min(axis=1, initial=w - 1.0)
        lo = np.ceil(bound[:, ~right]).max(axis=1, initial=0.0)
    # flat edges: the exact test at both ends of the row (monotone in x in between)
    flat = ~steep
    empty = np.zeros(h, bool)
    unsure = np.zeros(h, bool)
    if flat.any():
        fn, fo = normals[flat], offsets[flat]
        ends = [_edge_distances(fn, fo, np.full(h, c, np.float64), rows) <= margin
                for c in (0.0, w - 1.0)]
        empty = (~ends[0] & ~ends[1]).any(axis=1)
        unsure = (ends[0] != ends[1]).any(axis=1) & ~empty
    if jit_available():
        inside = np.empty(len(x), bool)
        check = np.empty(len(x), bool)
        _classify_by_spans(x, y, lo, hi, empty, unsure, inside, check)
    else:  # the same rule in NumPy (a dozen passes over the events)
        xf = x.astype(np.float64)
        lo_e, hi_e = lo[y], hi[y]
        sure_row = ~unsure[y]
        inside = sure_row & ~empty[y] & (xf >= lo_e + 2) & (xf <= hi_e - 2)
        outside = sure_row & (empty[y] | (xf < lo_e - 2) | (xf > hi_e + 2))
        check = ~(inside | outside)
    if check.any():
        inside[check] = _outside_distance(normals, offsets, x[check].astype(np.float64),
                                          y[check].astype(np.float64)) <= margin
    return inside


@njit
def _steep_spans(nx, ny, offsets, steep, margin, w, h, lo, hi):
    """Per row ``r < h``, the columns ``[lo[r], hi[r]]`` that the steep edges allow
    (``n_x * col <= margin + o - n_y * r``, rounded inwards; ``[0, w - 1]`` without such an
    edge): the NumPy form's (H, K) passes of :func:`pixels_in_polygon` in one loop nest."""
    for r in range(h):
        row = np.float64(r)
        lo_r, hi_r = 0.0, w - 1.0
        for k in range(nx.shape[0]):
            if steep[k]:
                bound = ((margin + offsets[k]) - row * ny[k]) / nx[k]
                if nx[k] > 0:
                    hi_r = min(hi_r, np.floor(bound))
                else:
                    lo_r = max(lo_r, np.ceil(bound))
        lo[r] = lo_r
        hi[r] = hi_r


@njit
def _classify_by_spans(x, y, lo, hi, empty, unsure, inside, check):
    """Per pixel ``i`` (row ``y[i]``): ``inside[i]`` when it lies more than 2 columns inside
    its row's span ``[lo, hi]`` (a sure row that is not empty), ``check[i]`` when it is
    neither that nor more than 2 columns outside (or its row is unsure): the rule of
    :func:`pixels_in_polygon` in one pass."""
    for i in range(x.shape[0]):
        r = y[i]
        xf = np.float64(x[i])
        if unsure[r]:
            inside[i] = False
            check[i] = True
        elif empty[r]:
            inside[i] = False
            check[i] = False
        else:
            within = xf >= lo[r] + 2 and xf <= hi[r] - 2
            out = xf < lo[r] - 2 or xf > hi[r] + 2
            inside[i] = within
            check[i] = not (within or out)


class Silhouette:
    """Project an object's convex hull at a pose (see the module docstring).

    Args:
        vertices: (V, 3) object-frame mesh vertices, metres (the hull is taken here).
        camera: the event camera.

    Example:
        >>> cam = PinholeCamera(100.0, 100.0, 49.5, 49.5, 100, 100)
        >>> cube = np.array([[x, y, z] for x in (-.1, .1) for y in (-.1, .1) for z in (-.1, .1)])
        >>> sil = Silhouette(cube, cam)
        >>> T = np.eye(4); T[2, 3] = 1.0
        >>> poly = sil.polygon(T)
        >>> bool(poly.contains(np.array([[49.5, 49.5]]))[0]), round(poly.visible_fraction, 2)
        (True, 1.0)
    """

    def __init__(self, vertices: np.ndarray, camera: PinholeCamera) -> None:
        self.camera = camera
        self.points = hull_vertices(vertices)
        self._points_t = torch.from_numpy(self.points)
        lo, hi = self.points.min(0), self.points.max(0)
        # the 8 corners of the hull's bounding box (object frame): in front of the camera and
        # projecting inside the image, they put every hull point there (the box is convex)
        self._box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                              for z in (lo[2], hi[2])])
        w, h = camera.width, camera.height
        self._image = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5],
                                [-0.5, h - 0.5]], np.float32)

    def _project(self, pose: np.ndarray | torch.Tensor, points: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray] | None:
        """Hull vertices (or ``points`` (V, 3), object frame) at ``pose``: pixels (V, 2) and
        depths (V,) metres, or ``None`` when a point is closer than :data:`MIN_DEPTH_M` (or not
        finite)."""
        T = np.asarray(pose, np.float64)
        P = (self.points if points is None else points) @ T[:3, :3].T + T[:3, 3]
        z = P[:, 2]
        if not np.isfinite(P).all() or z.min() < MIN_DEPTH_M:
            return None
        if self.camera.dist is None:
            uv = np.stack([self.camera.fx * P[:, 0] / z + self.camera.cx,
                           self.camera.fy * P[:, 1] / z + self.camera.cy], 1)
        else:
            uv = self.camera.project(torch.from_numpy(P)).numpy()
        return uv, z

    def box_in_image(self, t: tuple[float, float, float], q: tuple[float, float, float, float]
                     ) -> bool:
        """Whether the corners of the hull's bounding box lie in front of the camera and
        project inside the image at the pose ``(t (3,) m, q (4,) unit wxyz)``, so that the
        whole silhouette is in view (:meth:`visible_fraction` is 1). False: not known here
        (a corner outside, or a distorted camera); ask :meth:`visible_fraction`. One compiled
        call of ~2 µs: the tracker asks at every velocity step."""
        cam = self.camera
        if cam.dist is not None:
            return False
        return bool(_box_in_image(tuple(t), tuple(q), self._box, float(cam.fx), float(cam.fy),
                                  float(cam.cx), float(cam.cy), float(cam.width),
                                  float(cam.height), MIN_DEPTH_M))

    def boxes_in_image(self, t: np.ndarray, q: np.ndarray) -> np.ndarray:
        """:meth:`box_in_image` at ``n`` poses in one compiled call: ``t`` (n, 3) m, ``q``
        (n, 4) unit wxyz -> (n,) bool. For the tracker's runs of velocity steps.

        Raises:
            ValueError: ``t`` and ``q`` not (n, 3) and (n, 4).
        """
        t = np.ascontiguousarray(t, np.float64)
        q = np.ascontiguousarray(q, np.float64)
        if t.ndim != 2 or t.shape[1] != 3 or q.shape != (len(t), 4):
            raise ValueError(f"Silhouette.boxes_in_image: t must be (n, 3) and q (n, 4), got "
                             f"{t.shape} and {q.shape}")
        cam = self.camera
        if cam.dist is not None:
            return np.zeros(len(t), bool)
        return _boxes_in_image(t, q, self._box, float(cam.fx), float(cam.fy), float(cam.cx),
                               float(cam.cy), float(cam.width), float(cam.height),
                               MIN_DEPTH_M)

    def visible_fraction(self, pose: np.ndarray | torch.Tensor) -> float:
        """``polygon(pose).visible_fraction`` (0 without a polygon), in [0, 1]: 1 at once when
        the corners of the hull's bounding box lie in front of the camera and project inside
        the image (then so does the whole hull), without projecting the hull or building the
        polygon; the tracker asks at every step."""
        corners = self._project(pose, self._box) if self.camera.dist is None else None
        if corners is not None:
            uv = corners[0]
            w, h = self.camera.width, self.camera.height
            if ((uv >= -0.5).all() and (uv[:, 0] < w - 0.5).all()
                    and (uv[:, 1] < h - 0.5).all()):
                return 1.0
        poly = self.polygon(pose)
        return 0.0 if poly is None else poly.visible_fraction

    def polygon(self, pose: np.ndarray | torch.Tensor) -> SilhouettePolygon | None:
        """The silhouette at an object-to-camera pose (4, 4); ``None`` when the object is not in
        front of the camera (a hull vertex closer than :data:`MIN_DEPTH_M`)."""
        projected = self._project(pose)
        if projected is None:
            return None
        uv, z = projected
        return self._hull_polygon(uv, float(z.min()), float(z.max()))

    def hull(self, polygons: list[SilhouettePolygon]) -> SilhouettePolygon:
        """The convex hull of silhouettes (e.g. at the start and the end of a motion), as
        one :class:`SilhouettePolygon`: its depth range spans theirs. For a convex silhouette
        moved by a translation it is exactly the area swept between the two positions.

        Raises:
            ValueError: no polygon given.
        """
        if not polygons:
            raise ValueError("Silhouette.hull needs at least one polygon")
        uv = np.concatenate([p.vertices for p in polygons])
        return self._hull_polygon(uv, min(p.z_range[0] for p in polygons),
                                  max(p.z_range[1] for p in polygons))

    def _hull_polygon(self, uv: np.ndarray, z_min: float, z_max: float) -> SilhouettePolygon:
        """(N, 2) pixels -> their convex hull, with the share of its area in the image."""
        hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
        area = abs(cv2.contourArea(hull))
        if area > 0:
            inter, _ = cv2.intersectConvexConvex(hull, self._image)
            visible = float(min(max(inter / area, 0.0), 1.0))
        else:
            cx, cy = hull.mean(0)
            inside = -0.5 <= cx < self.camera.width - 0.5 and -0.5 <= cy < self.camera.height - 0.5
            visible = 1.0 if inside else 0.0
        return SilhouettePolygon(hull.astype(np.float64), (z_min, z_max), visible)


@njit
def _box_in_image(t, q, box, fx, fy, cx, cy, w, h, min_depth):
    """:meth:`Silhouette.box_in_image` on floats: ``box`` (8, 3) object-frame corners."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rotation_matrix(q)
    for i in range(box.shape[0]):
        bx, by, bz = box[i, 0], box[i, 1], box[i, 2]
        x = r00 * bx + r01 * by + r02 * bz + t[0]
        y = r10 * bx + r11 * by + r12 * bz + t[1]
        z = r20 * bx + r21 * by + r22 * bz + t[2]
        if not z >= min_depth:  # NaN too
            return False
        u = fx * x / z + cx
        v = fy * y / z + cy
        if not (u >= -0.5 and u < w - 0.5 and v >= -0.5 and v < h - 0.5):
            return False
    return True


@njit
def _boxes_in_image(t, q, box, fx, fy, cx, cy, w, h, min_depth):
    """:func:`_box_in_image` at each row of ``t`` (n, 3) and ``q`` (n, 4) -> (n,) bool."""
    out = np.zeros(t.shape[0], np.bool_)
    for k in range(t.shape[0]):
        out[k] = _box_in_image((t[k, 0], t[k, 1], t[k, 2]),
                               (q[k, 0], q[k, 1], q[k, 2], q[k, 3]),
                               box, fx, fy, cx, cy, w, h, min_depth)
    return out
