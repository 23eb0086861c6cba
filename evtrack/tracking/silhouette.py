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

Whether the whole silhouette is in view, the tracker's question at every step, is answered
without the hull where it can be (:meth:`Silhouette.box_in_image`): when the 8 corners of the
hull's bounding box lie in front of the camera and their ideal (undistorted) pinhole
projections inside a rectangle whose every point the lens maps into the image
(:func:`ideal_view_rectangle`; without distortion, the image itself), every hull point's ideal
projection lies in that rectangle too (the box's projection is convex), and so its distorted
projection lies in the image.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.filters.scalar_lie import rotation_matrix
from evtrack.runtime.jit import available as jit_available
from evtrack.runtime.jit import njit

__all__ = ["Silhouette", "SilhouettePolygon", "hull_vertices", "ideal_view_rectangle",
           "pixels_in_polygon", "points_in_polygon"]

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


VIEW_INSET_PX = 0.25
""":func:`ideal_view_rectangle` seeks its rectangle for the image shrunk by this much (pixels)
on each side: room for its verification's bound on the lens's curvature between grid nodes."""

_GRID_NODES = 257
"""At most this many grid nodes per axis verify :func:`ideal_view_rectangle`'s rectangle."""

_SHRINK_ROUNDS = 64
"""At most this many rounds of shrinking :func:`ideal_view_rectangle`'s rectangle."""


def ideal_view_rectangle(camera: PinholeCamera) -> tuple[float, float, float, float] | None:
    """A rectangle of ideal (undistorted) pixels ``u = fx * x / z + cx``, ``v = fy * y / z + cy``
    that the camera's lens maps, every point of it, inside the image
    ``[-0.5, W - 0.5) x [-0.5, H - 0.5)``: a point projecting into it is surely in view.

    Without distortion it is the image itself. With distortion, the image's boundary shrunk by
    :data:`VIEW_INSET_PX` is undistorted (``PinholeCamera.undistort_points``, samples 1 px
    apart) and each side of the rectangle placed at the innermost undistorted point of its
    edge (the largest ``u`` of the left edge, ...). The rectangle is then verified: a grid of
    up to 257 x 257 nodes over it (its sides included) is distorted
    (``PinholeCamera.distort_points``) and every node must land at least ``e`` inside the
    image. A point of a grid cell lands within the bilinear interpolation error of the convex
    hull of its corners' images, at most ``(g_u² max|∂²D/∂u²| + g_v² max|∂²D/∂v²|) / 8``
    (cell sides ``g``); ``e`` takes the largest second differences of the nodes' images
    along each axis for ``g² |∂²D|`` and doubles that bound, plus 1e-3 px for rounding. The
    sides nearest the nodes that fail (or do not distort to finite pixels) move inwards past
    them, a cell at least, and the grid is checked again. Computed once per set of camera
    parameters (cached).

    Args:
        camera: the event camera.

    Returns:
        ``(u_lo, u_hi, v_lo, v_hi)`` pixels, the rectangle ``[u_lo, u_hi) x [v_lo, v_hi)``;
        ``None`` where no rectangle of at least one pixel a side was verified.
    """
    if camera.dist is None:
        return (-0.5, camera.width - 0.5, -0.5, camera.height - 0.5)
    return _distorted_view_rectangle(camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                                     camera.height, tuple(float(d) for d in camera.dist))


@lru_cache(maxsize=32)
def _distorted_view_rectangle(fx: float, fy: float, cx: float, cy: float, w: int, h: int,
                              dist: tuple[float, ...]
                              ) -> tuple[float, float, float, float] | None:
    """:func:`ideal_view_rectangle` of a camera with distortion ``dist``, by its parameters."""
    cam = PinholeCamera(fx, fy, cx, cy, w, h, dist)
    rect = _undistorted_edges_rectangle(cam)
    for _ in range(_SHRINK_ROUNDS):
        u_lo, u_hi, v_lo, v_hi = rect
        if not (u_hi - u_lo >= 1.0 and v_hi - v_lo >= 1.0):
            return None
        gu = np.linspace(u_lo, u_hi, _GRID_NODES)
        gv = np.linspace(v_lo, v_hi, _GRID_NODES)
        nodes = np.stack(np.meshgrid(gu, gv), -1)  # (V, U, 2): row j at gv[j], column i at gu[i]
        bad = _nodes_outside(cam, nodes)
        if not bad.any():
            return rect
        rect = _shrink_past(rect, nodes[bad], gu[1] - gu[0], gv[1] - gv[0])
    return None


def _undistorted_edges_rectangle(cam: PinholeCamera) -> tuple[float, float, float, float]:
    """The first guess of :func:`ideal_view_rectangle`: the innermost undistorted points of
    the four edges of the image shrunk by :data:`VIEW_INSET_PX`. Only the points that the
    lens maps back to within 0.01 px of their edge count (the iterative undistortion does not
    converge where the lens model cannot reach an edge pixel, e.g. a strong barrel's
    corners); an edge with none keeps its own position."""
    lo_u, hi_u = -0.5 + VIEW_INSET_PX, cam.width - 0.5 - VIEW_INSET_PX
    lo_v, hi_v = -0.5 + VIEW_INSET_PX, cam.height - 0.5 - VIEW_INSET_PX
    us = np.linspace(lo_u, hi_u, cam.width + 1)
    vs = np.linspace(lo_v, hi_v, cam.height + 1)
    edges = [np.stack([np.full_like(vs, lo_u), vs], 1), np.stack([np.full_like(vs, hi_u), vs], 1),
             np.stack([us, np.full_like(us, lo_v)], 1), np.stack([us, np.full_like(us, hi_v)], 1)]
    pixels = np.concatenate(edges)
    ideal = cam.undistort_points(torch.from_numpy(pixels)).numpy()
    back = _distort(cam, ideal)
    with np.errstate(invalid="ignore"):
        converged = (np.abs(back - pixels) <= 0.01).all(1)
    cuts = np.cumsum([len(e) for e in edges])[:-1]
    sides = []
    for ideal_k, ok, (axis, inner, own) in zip(
            np.split(ideal, cuts), np.split(converged, cuts),
            ((0, np.max, lo_u), (0, np.min, hi_u), (1, np.max, lo_v), (1, np.min, hi_v)),
            strict=True):
        sides.append(float(inner(ideal_k[ok, axis])) if ok.any() else own)
    return sides[0], sides[1], sides[2], sides[3]


_DISTORT_CHUNK = 16384
"""Points per ``distort_points`` call in :func:`_distort`: below torch's size for its
intra-op threads (which, on a busy machine, cost far more than they save here)."""


def _distort(cam: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    """``cam.distort_points`` of (N, 2) ideal pixels -> (N, 2) float64 distorted pixels."""
    out = np.empty_like(uv)
    for i in range(0, len(uv), _DISTORT_CHUNK):
        chunk = torch.from_numpy(np.ascontiguousarray(uv[i:i + _DISTORT_CHUNK]))
        out[i:i + _DISTORT_CHUNK] = cam.distort_points(chunk).numpy()
    return out


def _nodes_outside(cam: PinholeCamera, nodes: np.ndarray) -> np.ndarray:
    """(V, U) bool: the grid nodes (V, U, 2) ideal pixels whose distorted pixels are not finite
    or lie less than the interpolation bound of :func:`ideal_view_rectangle` inside the
    image."""
    d = _distort(cam, nodes.reshape(-1, 2)).reshape(nodes.shape)
    with np.errstate(invalid="ignore"):
        along_u = np.abs(d[:, 2:] - 2.0 * d[:, 1:-1] + d[:, :-2])
        along_v = np.abs(d[2:] - 2.0 * d[1:-1] + d[:-2])
        if np.isfinite(along_u).all() and np.isfinite(along_v).all():
            e = 1e-3 + 2.0 * (along_u.max() + along_v.max()) / 8.0
        else:
            e = np.inf  # a singular lens model within the rectangle: every node fails
        du, dv = d[..., 0], d[..., 1]
        inside = ((du >= -0.5 + e) & (du <= cam.width - 0.5 - e) & (dv >= -0.5 + e)
                  & (dv <= cam.height - 0.5 - e))
    return ~inside


def _shrink_past(rect: tuple[float, float, float, float], bad: np.ndarray, gu: float,
                 gv: float) -> tuple[float, float, float, float]:
    """``rect`` ``(u_lo, u_hi, v_lo, v_hi)`` with the side nearest each of the ``bad`` (N, 2)
    points (relative to the rectangle's half sides) moved a grid cell (``gu``, ``gv`` px)
    past the innermost of them."""
    u_lo, u_hi, v_lo, v_hi = rect
    a = (bad[:, 0] - 0.5 * (u_lo + u_hi)) / (0.5 * (u_hi - u_lo))
    b = (bad[:, 1] - 0.5 * (v_lo + v_hi)) / (0.5 * (v_hi - v_lo))
    horizontal = np.abs(a) >= np.abs(b)
    if (horizontal & (a < 0)).any():
        u_lo = float(bad[horizontal & (a < 0), 0].max()) + gu
    if (horizontal & (a >= 0)).any():
        u_hi = float(bad[horizontal & (a >= 0), 0].min()) - gu
    if (~horizontal & (b < 0)).any():
        v_lo = float(bad[~horizontal & (b < 0), 1].max()) + gv
    if (~horizontal & (b >= 0)).any():
        v_hi = float(bad[~horizontal & (b >= 0), 1].min()) - gv
    return u_lo, u_hi, v_lo, v_hi


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
        self._view_rect = ideal_view_rectangle(camera)
        """``(u_lo, u_hi, v_lo, v_hi)`` ideal pixels (:func:`ideal_view_rectangle`) or None."""

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

    def _kernel_frame(self) -> tuple[float, float, float, float] | None:
        """The view rectangle ``[u_lo, u_hi) x [v_lo, v_hi)`` as the compiled kernels' image:
        principal point ``(cx - u_lo - 0.5, cy - v_lo - 0.5)`` and size ``(u_hi - u_lo,
        v_hi - v_lo)`` pixels, so that their test ``-0.5 <= u' < W' - 0.5`` on
        ``u' = u - u_lo - 0.5`` is ``u_lo <= u < u_hi`` (to rounding, ~1e-13 px, which the
        rectangle's margin covers; exactly the image's test without distortion, whose
        rectangle gives ``cx``, ``W`` unchanged); None without a rectangle."""
        if self._view_rect is None:
            return None
        u_lo, u_hi, v_lo, v_hi = self._view_rect
        cam = self.camera
        return (float(cam.cx) - (u_lo + 0.5), float(cam.cy) - (v_lo + 0.5), u_hi - u_lo,
                v_hi - v_lo)

    def box_in_image(self, t: tuple[float, float, float], q: tuple[float, float, float, float]
                     ) -> bool:
        """Whether the corners of the hull's bounding box lie in front of the camera and
        their ideal projections inside the view rectangle (:func:`ideal_view_rectangle`: the
        image without distortion) at the pose ``(t (3,) m, q (4,) unit wxyz)``, so that the
        whole silhouette is in view (:meth:`visible_fraction` is 1). False: not known here
        (a corner outside the rectangle, or a lens without one); ask :meth:`visible_fraction`.
        One compiled call of ~2 µs: the tracker asks at every velocity step."""
        frame = self._kernel_frame()
        if frame is None:
            return False
        cam = self.camera
        cx, cy, w, h = frame
        return bool(_box_in_image(tuple(t), tuple(q), self._box, float(cam.fx), float(cam.fy),
                                  cx, cy, w, h, MIN_DEPTH_M))

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
        frame = self._kernel_frame()
        if frame is None:
            return np.zeros(len(t), bool)
        cam = self.camera
        cx, cy, w, h = frame
        return _boxes_in_image(t, q, self._box, float(cam.fx), float(cam.fy), cx, cy, w, h,
                               MIN_DEPTH_M)

    def visible_fraction(self, pose: np.ndarray | torch.Tensor) -> float:
        """``polygon(pose).visible_fraction`` (0 without a polygon), in [0, 1]: 1 at once when
        the corners of the hull's bounding box lie in front of the camera and their ideal
        projections inside the view rectangle (:meth:`box_in_image`'s test, in NumPy), without
        projecting the hull or building the polygon; the tracker asks at every step.

        Args:
            pose: (4, 4) object-to-camera transform, metres.
        """
        if self._view_rect is not None:
            T = np.asarray(pose, np.float64)
            P = self._box @ T[:3, :3].T + T[:3, 3]
            z = P[:, 2]
            if np.isfinite(P).all() and z.min() >= MIN_DEPTH_M:
                u_lo, u_hi, v_lo, v_hi = self._view_rect
                u = self.camera.fx * P[:, 0] / z + self.camera.cx
                v = self.camera.fy * P[:, 1] / z + self.camera.cy
                if ((u >= u_lo).all() and (u < u_hi).all() and (v >= v_lo).all()
                        and (v < v_hi).all()):
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
        w, h = self.camera.width, self.camera.height
        if area > 0 and ((hull >= -0.5).all() and (hull[:, 0] <= w - 0.5).all()
                         and (hull[:, 1] <= h - 0.5).all()):
            # the hull in the image's closed rectangle: all of it inside, exactly (the
            # intersection's area below is rounded to float32, its ratio to ``area`` not 1)
            visible = 1.0
        elif area > 0:
            inter, _ = cv2.intersectConvexConvex(hull, self._image)
            visible = float(min(max(inter / area, 0.0), 1.0))
        else:
            cx, cy = hull.mean(0)
            inside = -0.5 <= cx < w - 0.5 and -0.5 <= cy < h - 0.5
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
