"""Seeded procedural textures: printed packaging, labels and backgrounds.

All functions return ``(H, W, 3) uint8`` sRGB images (row 0 at the top) and draw with OpenCV
from a :class:`numpy.random.Generator`, so the same generator state gives the same pixels.
They are designed to have plenty of edges (text, stripes, shapes) so that moving objects
produce events everywhere, as printed packaging does.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = [
    "random_color",
    "printed_panel",
    "spread_colors",
    "label_band",
    "background_texture",
    "checker_texture",
    "hatch",
    "corner_palette",
    "corner_coded_panel",
]

_LETTERS = "ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789"
_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_TRIPLEX,
          cv2.FONT_HERSHEY_COMPLEX)


def random_color(rng: np.random.Generator, saturated: bool = True) -> tuple[int, int, int]:
    """A random sRGB colour; ``saturated`` picks a vivid hue (HSV with high S and V)."""
    if not saturated:
        return tuple(int(v) for v in rng.integers(0, 256, 3))
    hsv = np.array([[[rng.integers(0, 180), rng.integers(150, 256), rng.integers(140, 256)]]],
                   dtype=np.uint8)
    return tuple(int(v) for v in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0])


def spread_colors(rng: np.random.Generator, count: int) -> list[tuple[int, int, int]]:
    """``count`` vivid sRGB colours with hues evenly spread around the wheel, in a seeded
    order from a seeded start (distinct faces of one object)."""
    start = int(rng.integers(0, 180))
    hues = (start + np.arange(count) * 180 // count) % 180
    colors = []
    for h in rng.permutation(hues):
        hsv = np.array([[[h, rng.integers(150, 256), rng.integers(140, 256)]]], dtype=np.uint8)
        colors.append(tuple(int(v) for v in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]))
    return colors


def _contrasting(color: tuple[int, int, int]) -> tuple[int, int, int]:
    lum = 0.299 * color[0] + 0.587 * color[1] + 0.114 * color[2]
    return (245, 245, 240) if lum < 128 else (20, 20, 25)


def hatch(img: np.ndarray, base: tuple[int, int, int], spacing: int | None = None,
          darkness: float = 0.7, thickness: int | None = None) -> None:
    """Draw a fine diagonal hatching in a darker shade of ``base`` (``darkness`` times its
    value) over ``img`` (in place): lines ``spacing`` pixels apart along a row, ``thickness``
    pixels thick (default a third of the spacing).

    Printed packaging is rarely flat; the hatching gives every area edges, hence events.
    """
    h, w = img.shape[:2]
    shade = tuple(int(v) for v in np.clip(np.array(base) * darkness, 0, 255))
    spacing = spacing or max(6, w // 90)
    thickness = thickness or max(1, spacing // 3)
    for k in range(-h, w + h, spacing):
        cv2.line(img, (k, 0), (k + h, h), shade, thickness, cv2.LINE_AA)


def _word(rng: np.random.Generator, lo: int, hi: int) -> str:
    return "".join(rng.choice(list(_LETTERS), int(rng.integers(lo, hi + 1))))


def _put_text_fit(img: np.ndarray, text: str, box: tuple[int, int, int, int], color,
                  font: int, thickness: int) -> None:
    """Draw ``text`` scaled to fit ``box = (x0, y0, x1, y1)``."""
    x0, y0, x1, y1 = box
    (tw, th), base = cv2.getTextSize(text, font, 1.0, thickness)
    scale = min((x1 - x0) / max(tw, 1), (y1 - y0) / max(th + base, 1))
    if scale <= 0:
        return
    thick = max(1, int(round(thickness * scale)))
    (tw, th), base = cv2.getTextSize(text, font, scale, thick)
    org = (x0 + ((x1 - x0) - tw) // 2, y0 + ((y1 - y0) + th) // 2)
    cv2.putText(img, text, org, font, scale, color, thick, cv2.LINE_AA)


def printed_panel(rng: np.random.Generator, width: int, height: int,
                  base: tuple[int, int, int] | None = None) -> np.ndarray:
    """One face of a printed box: a brand word, stripes, shapes and lines of small text.

    Args:
        rng: random generator (consumed).
        width, height: image size in pixels.
        base: background colour; random if ``None``.

    Returns:
        (height, width, 3) uint8 sRGB.
    """
    base = random_color(rng) if base is None else base
    ink = _contrasting(base)
    accent = random_color(rng)
    img = np.empty((height, width, 3), np.uint8)
    img[:] = base
    hatch(img, base)
    # diagonal or horizontal stripes
    for _ in range(int(rng.integers(2, 5))):
        y = int(rng.integers(0, height))
        thick = int(rng.integers(max(2, height // 60), max(3, height // 12)))
        slope = int(rng.integers(-height // 4, height // 4 + 1))
        cv2.line(img, (0, y), (width, y + slope), random_color(rng), thick, cv2.LINE_AA)
    # a coloured banner with the brand word
    by0 = int(height * rng.uniform(0.08, 0.3))
    by1 = by0 + int(height * rng.uniform(0.15, 0.25))
    cv2.rectangle(img, (int(0.05 * width), by0), (int(0.95 * width), by1), accent, -1)
    _put_text_fit(img, _word(rng, 4, 8), (int(0.08 * width), by0, int(0.92 * width), by1),
                  _contrasting(accent), int(rng.choice(_FONTS)), 3)
    # a few shapes (a "product photo")
    for _ in range(int(rng.integers(2, 6))):
        c = (int(rng.integers(0, width)), int(rng.integers(by1, height)))
        r = int(rng.integers(max(3, width // 30), max(4, width // 7)))
        if rng.random() < 0.5:
            cv2.circle(img, c, r, random_color(rng), -1, cv2.LINE_AA)
            cv2.circle(img, c, r, ink, max(1, r // 8), cv2.LINE_AA)
        else:
            cv2.rectangle(img, (c[0] - r, c[1] - r // 2), (c[0] + r, c[1] + r // 2),
                          random_color(rng), -1)
    # lines of small text
    y = by1 + int(height * 0.08)
    line_h = max(6, height // 25)
    while y + line_h < height * 0.97:
        x0 = int(width * rng.uniform(0.04, 0.15))
        x1 = int(width * rng.uniform(0.6, 0.95))
        _put_text_fit(img, " ".join(_word(rng, 2, 6) for _ in range(4)), (x0, y, x1, y + line_h),
                      ink, cv2.FONT_HERSHEY_SIMPLEX, 1)
        y += int(line_h * rng.uniform(1.5, 3.0))
    cv2.rectangle(img, (0, 0), (width - 1, height - 1), ink, max(2, width // 100))
    return img


def corner_palette(rng: np.random.Generator, count: int = 8) -> list[tuple[int, int, int]]:
    """``count`` vivid sRGB colours, hues evenly spread (45° apart for 8), high saturation and
    value, in a seeded order from a seeded start: colours that stay apart under lighting,
    blur, noise and small hue jitter (one per box corner)."""
    start = int(rng.integers(0, 180))
    hues = (start + np.arange(count) * 180 // count) % 180
    colors = []
    for h in rng.permutation(hues):
        hsv = np.array([[[h, rng.integers(200, 256), rng.integers(215, 256)]]], dtype=np.uint8)
        colors.append(tuple(int(v) for v in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]))
    return colors


def corner_coded_panel(rng: np.random.Generator, width: int, height: int,
                       quadrant_colors: tuple) -> np.ndarray:
    """One face of a corner-coded box: four quadrants, each on the colour of the box corner
    it touches, with hatching and lines of small dark text (edges for events) and a dark rim.

    Args:
        rng: random generator (consumed).
        width, height: image size in pixels.
        quadrant_colors: sRGB colours of the ``(top-left, top-right, bottom-left,
            bottom-right)`` quadrants.

    Returns:
        (height, width, 3) uint8 sRGB.
    """
    img = np.empty((height, width, 3), np.uint8)
    hw, hh = width // 2, height // 2
    ink = (25, 25, 30)
    for k, (r0, r1, c0, c1) in enumerate(((0, hh, 0, hw), (0, hh, hw, width),
                                          (hh, height, 0, hw), (hh, height, hw, width))):
        quad = img[r0:r1, c0:c1]
        quad[:] = quadrant_colors[k]
        hatch(quad, quadrant_colors[k], spacing=14, darkness=0.5, thickness=2)
        qh, qw = quad.shape[:2]
        line_h = max(5, qh // 9)
        y = int(qh * rng.uniform(0.25, 0.4))
        while y + line_h < qh * 0.8:  # text kept off the corner itself
            x0 = int(qw * rng.uniform(0.15, 0.3))
            x1 = int(qw * rng.uniform(0.6, 0.85))
            _put_text_fit(quad, " ".join(_word(rng, 2, 5) for _ in range(3)),
                          (x0, y, x1, y + line_h), ink, cv2.FONT_HERSHEY_SIMPLEX, 1)
            y += int(line_h * rng.uniform(1.6, 2.6))
    cv2.rectangle(img, (0, 0), (width - 1, height - 1), ink, max(2, width // 100))
    return img


def label_band(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """A wrap-around label (for cans and bottles): bands, a brand word repeated, a pattern.

    The left and right edges meet on the object, so the pattern is drawn without a gap.

    Returns:
        (height, width, 3) uint8 sRGB.
    """
    base = random_color(rng)
    img = np.empty((height, width, 3), np.uint8)
    img[:] = base
    hatch(img, base)
    # horizontal bands at top and bottom
    for frac0, frac1 in ((0.0, rng.uniform(0.08, 0.18)), (rng.uniform(0.82, 0.92), 1.0)):
        band = img[int(frac0 * height):int(frac1 * height)]
        color = random_color(rng)
        band[:] = color
        hatch(band, color, spacing=max(6, width // 60))
    # brand word repeated around
    repeats = int(rng.integers(2, 4))
    cell = width // repeats
    word = _word(rng, 4, 7)
    font = int(rng.choice(_FONTS))
    ink = _contrasting(base)
    for k in range(repeats):
        _put_text_fit(img, word, (k * cell + cell // 10, int(0.25 * height),
                                  (k + 1) * cell - cell // 10, int(0.5 * height)), ink, font, 3)
    # a row of circles or diamonds
    n = int(rng.integers(6, 16))
    r = max(3, int(min(width / n / 3, height * 0.08)))
    y = int(0.65 * height)
    for k in range(n):
        c = (int((k + 0.5) * width / n), y)
        color = random_color(rng)
        if rng.random() < 0.5:
            cv2.circle(img, c, r, color, -1, cv2.LINE_AA)
        else:
            pts = np.array([[c[0], c[1] - r], [c[0] + r, c[1]], [c[0], c[1] + r],
                            [c[0] - r, c[1]]], np.int32)
            cv2.fillConvexPoly(img, pts, color, cv2.LINE_AA)
    # small text lines
    line_h = max(5, height // 30)
    for k in range(3):
        yk = int(0.74 * height) + k * int(1.6 * line_h)
        _put_text_fit(img, " ".join(_word(rng, 2, 5) for _ in range(6)),
                      (int(0.05 * width), yk, int(0.6 * width), yk + line_h), ink,
                      cv2.FONT_HERSHEY_SIMPLEX, 1)
    return img


def background_texture(rng: np.random.Generator, width: int, height: int,
                       contrast: float = 0.35) -> np.ndarray:
    """A static room-like background: smooth multi-scale noise, a few panels and lines.

    Args:
        contrast: in [0, 1]; 0 gives a flat grey.

    Returns:
        (height, width, 3) uint8 sRGB.
    """
    img = np.zeros((height, width, 3), np.float32)
    for scale, weight in ((4, 0.2), (16, 0.4), (64, 0.4)):  # fine grain to large blotches
        small = rng.random((max(2, height // scale), max(2, width // scale), 3)).astype(np.float32)
        img += weight * cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    tint = np.array(random_color(rng, saturated=False), np.float32) / 255.0
    img = 0.5 + contrast * (img - 0.5) + 0.15 * (tint - 0.5)
    out = np.clip(img * 255.0, 0, 255).astype(np.uint8)
    for _ in range(int(rng.integers(3, 8))):
        x0, y0 = int(rng.integers(0, width)), int(rng.integers(0, height))
        w = int(rng.integers(width // 12, width // 3))
        h = int(rng.integers(height // 12, height // 3))
        color = tuple(int(v) for v in np.clip(
            128 + contrast * (np.array(random_color(rng)) - 128), 0, 255))
        cv2.rectangle(out, (x0, y0), (x0 + w, y0 + h), color, -1)
    for _ in range(int(rng.integers(2, 6))):
        p0 = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        p1 = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        cv2.line(out, p0, p1, (int(128 * (1 - contrast)),) * 3, max(1, width // 200), cv2.LINE_AA)
    return out


def checker_texture(size: int, cells: int, colors: tuple[tuple[int, int, int], ...]) -> np.ndarray:
    """A checkerboard with ``cells`` x ``cells`` squares cycling through ``colors``.

    Used by tests: large uniform squares make texture lookups checkable away from edges.
    """
    img = np.empty((size, size, 3), np.uint8)
    step = size // cells
    for i in range(cells):
        for j in range(cells):
            color = colors[(i * cells + j) % len(colors)]
            img[i * step:(i + 1) * step, j * step:(j + 1) * step] = color
    return img
