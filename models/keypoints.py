"""Output-grid conventions and sub-pixel peak finding on belief maps.

Grid convention (shared by target generation and decoding): with output stride ``s``, cell
``(i, j)`` of a map covers input pixels ``[s*j, s*j + s) x [s*i, s*i + s)`` and stands for its
centre, the pixel ``(s*j + (s-1)/2, s*i + (s-1)/2)`` (pixel centres at integer coordinates).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.ndimage import maximum_filter

__all__ = ["grid_to_pixel", "pixel_to_grid", "find_peaks", "sample_bilinear", "SUBPIXEL_METHODS"]

SUBPIXEL_METHODS = ("log_quadratic", "centroid", "none")
_LOG_FLOOR = 1e-12  # values below this are treated as zero when taking logarithms


def grid_to_pixel(g: np.ndarray | float, stride: int) -> np.ndarray | float:
    """Grid coordinates (cells, any shape) -> input-image pixel coordinates."""
    return g * stride + (stride - 1) / 2.0


def pixel_to_grid(p: np.ndarray | float, stride: int) -> np.ndarray | float:
    """Input-image pixel coordinates (any shape) -> grid coordinates (cells)."""
    return (p - (stride - 1) / 2.0) / stride


def _log_quadratic_offset(lm: np.ndarray, l0: np.ndarray, lp: np.ndarray) -> np.ndarray:
    """Vertex offset (in [-0.5, 0.5]) of the parabola through (-1, lm), (0, l0), (1, lp).

    0 where the parabola is not concave. On log-values this is exact for a sampled Gaussian
    (its logarithm is a parabola).
    """
    denom = lm - 2.0 * l0 + lp  # twice the quadratic coefficient
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(denom < 0, 0.5 * (lm - lp) / denom, 0.0)
    return np.clip(off, -0.5, 0.5)


def _refine(
    m: np.ndarray, ys: np.ndarray, xs: np.ndarray, method: str, radius: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refined x, y (cells) and peak values of the peaks at integer ``(ys, xs)``."""
    h, w = m.shape
    fx = xs.astype(np.float64)
    fy = ys.astype(np.float64)
    vals = m[ys, xs].astype(np.float64)
    if method == "none" or len(xs) == 0:
        return fx, fy, vals
    if method == "log_quadratic":

        def logm(yy: np.ndarray, xx: np.ndarray) -> np.ndarray:  # only the cells needed
            return np.log(np.maximum(m[yy, xx].astype(np.float64), _LOG_FLOOR))

        inner_x = (xs > 0) & (xs < w - 1)
        inner_y = (ys > 0) & (ys < h - 1)
        xm, xp = np.clip(xs - 1, 0, w - 1), np.clip(xs + 1, 0, w - 1)
        ym, yp = np.clip(ys - 1, 0, h - 1), np.clip(ys + 1, 0, h - 1)
        centre = logm(ys, xs)
        ox = _log_quadratic_offset(logm(ys, xm), centre, logm(ys, xp))
        oy = _log_quadratic_offset(logm(ym, xs), centre, logm(yp, xs))
        # the value stays the cell's: the fitted height extrapolates wildly on flat-topped or
        # one-sided peaks (a neighbour near zero makes its logarithm huge), and a ranking by
        # it let spurious border peaks outrank the real keypoint
        return fx + np.where(inner_x, ox, 0.0), fy + np.where(inner_y, oy, 0.0), vals
    # weighted centroid of the positive values in a (2r+1)^2 window
    out_x, out_y = fx.copy(), fy.copy()
    for n, (y, x) in enumerate(zip(ys, xs, strict=True)):
        y0, y1 = max(0, y - radius), min(h, y + radius + 1)
        x0, x1 = max(0, x - radius), min(w, x + radius + 1)
        win = np.maximum(m[y0:y1, x0:x1].astype(np.float64), 0.0)
        total = win.sum()
        if total > 0:
            gy, gx = np.mgrid[y0:y1, x0:x1]
            out_x[n] = (win * gx).sum() / total
            out_y[n] = (win * gy).sum() / total
    return out_x, out_y, vals


def find_peaks(
    maps: np.ndarray,
    threshold: float,
    nms_radius: int = 1,
    subpixel: Literal["log_quadratic", "centroid", "none"] = "log_quadratic",
    centroid_radius: int = 2,
) -> list[np.ndarray]:
    """Local maxima of each map, refined to sub-cell precision.

    A cell is a peak when its value is ``>= threshold`` and the largest in the
    ``(2r+1) x (2r+1)`` window around it (``r = nms_radius``); of several equal maxima within
    ``r`` cells only the first (row-major) is kept.

    Sub-cell refinement: ``"log_quadratic"`` fits a parabola to the logarithms of the peak and
    its two neighbours along x and along y (exact for a Gaussian blob); ``"centroid"`` takes the
    value-weighted mean position over the ``(2c+1)^2`` window, ``c = centroid_radius``;
    ``"none"`` keeps the cell. The reported value is always the peak cell's (never a fitted
    height, which is unreliable on flat-topped or one-sided peaks).

    Args:
        maps: (C, h, w) belief maps.
        threshold: minimum peak value.
        nms_radius: suppression radius in cells (>= 1).
        subpixel: refinement method.

    Returns:
        C arrays of shape (n_c, 3): ``x, y`` in grid cells and the peak value, strongest first.
    """
    if maps.ndim != 3:
        raise ValueError(f"maps must be (C, h, w), got shape {maps.shape}")
    if subpixel not in SUBPIXEL_METHODS:
        raise ValueError(f"subpixel must be one of {SUBPIXEL_METHODS}, got {subpixel!r}")
    if nms_radius < 1:
        raise ValueError(f"nms_radius must be >= 1, got {nms_radius}")
    maps = np.asarray(maps, dtype=np.float32)
    size = 2 * nms_radius + 1
    pooled = maximum_filter(maps, size=(1, size, size), mode="constant", cval=-np.inf)
    is_peak = (maps >= pooled) & (maps >= threshold) & np.isfinite(maps)
    out: list[np.ndarray] = []
    for c in range(maps.shape[0]):
        ys, xs = np.nonzero(is_peak[c])
        # drop plateau duplicates: keep the first of equal maxima closer than the radius
        keep = np.ones(len(xs), dtype=bool)
        for a in range(len(xs)):
            if not keep[a]:
                continue
            close = (np.abs(xs[a + 1:] - xs[a]) <= nms_radius) & (
                np.abs(ys[a + 1:] - ys[a]) <= nms_radius
            )
            keep[a + 1:][close] = False
        ys, xs = ys[keep], xs[keep]
        px, py, vals = _refine(maps[c], ys, xs, subpixel, centroid_radius)
        order = np.argsort(-vals, kind="stable")
        out.append(np.stack([px[order], py[order], vals[order]], axis=-1).reshape(-1, 3))
    return out


def sample_bilinear(field: np.ndarray, x: float, y: float) -> np.ndarray:
    """Bilinearly sample a (C, h, w) field at grid point ``(x, y)`` (clamped to the border).

    Returns:
        (C,) float64.
    """
    _, h, w = field.shape
    x = float(np.clip(x, 0, w - 1))
    y = float(np.clip(y, 0, h - 1))
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    ax, ay = x - x0, y - y0

    def at(yy: int, xx: int) -> np.ndarray:  # the four corners only, not the whole field
        return field[:, yy, xx].astype(np.float64)

    top = at(y0, x0) * (1 - ax) + at(y0, x1) * ax
    bottom = at(y1, x0) * (1 - ax) + at(y1, x1) * ax
    return top * (1 - ay) + bottom * ay
