"""The corner-coded box: the texture around each cuboid corner has that corner's own colour on
all three faces that meet there, and the eight colours stay far apart."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from evtrack.sim.objects import make_box, make_coded_box


def _texel_colour_near_corners(mesh) -> dict[tuple[int, int, int], list[np.ndarray]]:
    """Median texture colour a little inside each face quad at each of its corners, grouped by
    the corner's octant (signs of x, y, z), read through the mesh's own UVs."""
    th, tw = mesh.texture.shape[:2]
    by_corner: dict[tuple[int, int, int], list[np.ndarray]] = {}
    for quad in range(len(mesh.faces) // 2):
        idx = np.unique(mesh.faces[2 * quad:2 * quad + 2])
        assert len(idx) == 4
        uv_centre = mesh.uv[idx].mean(0)
        for i in idx:
            uv = mesh.uv[i] + 0.12 * (uv_centre - mesh.uv[i])  # 12 % of the way to the centre
            col, row = uv[0] * (tw - 1), (1.0 - uv[1]) * (th - 1)
            patch = mesh.texture[int(row) - 7:int(row) + 8, int(col) - 7:int(col) + 8]
            octant = tuple(int(v) for v in np.sign(mesh.vertices[i]))
            by_corner.setdefault(octant, []).append(np.median(patch.reshape(-1, 3), axis=0))
    return by_corner


def _hue_deg(rgb: np.ndarray) -> float:
    hsv = cv2.cvtColor(np.uint8(np.round(rgb))[None, None], cv2.COLOR_RGB2HSV_FULL)[0, 0]
    return float(hsv[0]) * 360.0 / 256.0


def _hue_gap(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


@pytest.mark.parametrize("seed", [0, 3])
def test_each_corner_has_its_own_colour_on_all_its_faces(seed: int) -> None:
    mesh = make_coded_box(seed=seed)
    by_corner = _texel_colour_near_corners(mesh)
    assert len(by_corner) == 8 and all(len(v) == 3 for v in by_corner.values())
    hues = {}
    for octant, colours in by_corner.items():
        colours = np.array(colours)
        assert np.abs(colours - colours[0]).max() <= 12, (octant, colours)  # one colour
        hsv = cv2.cvtColor(np.uint8(colours)[None], cv2.COLOR_RGB2HSV)[0]
        assert hsv[:, 1].min() >= 150 and hsv[:, 2].min() >= 150  # vivid, not washed out
        hues[octant] = _hue_deg(colours[0])
    values = list(hues.values())
    gaps = [_hue_gap(a, b) for i, a in enumerate(values) for b in values[i + 1:]]
    assert min(gaps) >= 35.0  # 45° apart by design, minus 8-bit rounding


def test_the_ordinary_box_is_not_corner_coded() -> None:
    """The check above can fail: on the printed box, a corner's three faces differ in colour."""
    by_corner = _texel_colour_near_corners(make_box(seed=0))
    spread = [np.abs(np.array(c) - np.array(c)[0]).max() for c in by_corner.values()]
    assert max(spread) > 40


def test_same_geometry_as_the_box_and_seeded() -> None:
    coded, box = make_coded_box(seed=0), make_box(seed=0)
    np.testing.assert_array_equal(coded.vertices, box.vertices)
    np.testing.assert_array_equal(coded.uv, box.uv)
    assert coded.name == "coded_box" and coded.source == "procedural:coded_box:seed=0"
    assert np.array_equal(make_coded_box(seed=0).texture, coded.texture)
    assert not np.array_equal(make_coded_box(seed=1).texture, coded.texture)
