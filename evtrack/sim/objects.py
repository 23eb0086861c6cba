"""Textured objects for the simulator: meshes from files and seeded procedural objects.

Object frame: a mesh loaded from a file keeps its axes and units (metres; a BOP model, in
millimetres, is scaled to metres) but is recentred on its axis-aligned bounding-box centre
unless ``recenter=False``; :attr:`ObjectMesh.offset`
records the shift (``P_object = P_file - offset``). Procedural objects are built centred with
``y`` up (the axis of cans and bottles; the height of boxes) and ``z`` towards the front face.

Texture coordinates follow trimesh's (OBJ) convention: ``v`` grows upwards, ``(0, 0)`` is
the bottom-left corner of the texture image, whose row 0 is its top row.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh

from evtrack.errors import ConfigError
from evtrack.sim import textures
from evtrack.sim.errors import MeshFileError

__all__ = [
    "ObjectMesh",
    "load_mesh",
    "make_box",
    "make_coded_box",
    "make_can",
    "make_bottle",
    "procedural_object",
    "resolve_object",
    "find_ycb_dir",
    "PROCEDURAL_OBJECTS",
    "YCB_OBJECTS",
]

#: The four YCB objects of the paper's benchmark.
YCB_OBJECTS = ("003_cracker_box", "005_tomato_soup_can", "006_mustard_bottle",
               "010_potted_meat_can")
#: Names of the procedural objects (for the demo; no download needed).
PROCEDURAL_OBJECTS = ("box", "coded_box", "can", "bottle")

_SIZE_LIMITS_M = (0.005, 3.0)  # plausible object extents; outside them the units are wrong
_YCB_ENV = "EVTRACK_YCB_DIR"
_SEGMENTS = 96  # facets around cans and bottles
_TEXTURE_SIZE = 1024


@dataclass(frozen=True, eq=False)
class ObjectMesh:
    """A textured triangle mesh in its object frame (see the module docstring).

    Attributes:
        name: short name.
        vertices: (V, 3) float32 metres.
        faces: (F, 3) int32 vertex indices (counter-clockwise seen from outside).
        normals: (V, 3) float32 unit vertex normals.
        uv: (V, 2) float32 texture coordinates (trimesh/OBJ convention).
        texture: (Ht, Wt, 3) uint8 sRGB base colour image, row 0 at the top.
        colors: (V, 3) float32 linear colour multipliers (vertex colours, material factors).
        source: where it came from (a file path or ``procedural:<kind>:seed=<n>``).
        offset: (3,) float64 shift applied to the file's coordinates (zero if not recentred).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    texture: np.ndarray
    colors: np.ndarray
    source: str
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def extents(self) -> np.ndarray:
        """(3,) bounding-box size, metres."""
        return self.vertices.max(0) - self.vertices.min(0)

    @property
    def radius(self) -> float:
        """Radius of the bounding sphere about the object-frame origin, metres."""
        return float(np.linalg.norm(self.vertices, axis=1).max())

    def to_trimesh(self) -> trimesh.Trimesh:
        """A trimesh with this geometry and texture (for ray casting and export)."""
        from PIL import Image

        tex = self.texture
        uniform = np.allclose(self.colors, self.colors[:1])
        if not uniform and tex.shape[:2] == (1, 1):
            rgb = _linear_to_srgb_u8(self.colors * (tex[0, 0] / 255.0) ** 2.2)
            visual = trimesh.visual.ColorVisuals(vertex_colors=rgb)
        else:
            if not np.allclose(self.colors, 1.0):
                lin = (tex.astype(np.float32) / 255.0) ** 2.2 * self.colors[0]
                tex = _linear_to_srgb_u8(lin)
            material = trimesh.visual.material.PBRMaterial(
                baseColorTexture=Image.fromarray(tex), metallicFactor=0.0, roughnessFactor=1.0)
            visual = trimesh.visual.TextureVisuals(uv=self.uv, material=material)
        return trimesh.Trimesh(self.vertices, self.faces, vertex_normals=self.normals,
                               visual=visual, process=False)

    def export(self, path: str | Path) -> None:
        """Write the mesh (object frame, with its texture) to ``path``; GLB recommended."""
        from evtrack.utils import atomic_path

        path = Path(path)
        with atomic_path(path) as tmp:
            self.to_trimesh().export(tmp, file_type=path.suffix.lstrip(".").lower() or "glb")


def _linear_to_srgb_u8(lin: np.ndarray) -> np.ndarray:
    from evtrack.sim.frames import linear_to_srgb

    return linear_to_srgb(lin)


def _srgb_u8_to_linear(c: np.ndarray) -> np.ndarray:
    from evtrack.sim.frames import srgb_to_linear

    return srgb_to_linear(c)


# ---------------------------------------------------------------------------- files
def load_mesh(path: str | Path, *, name: str | None = None, recenter: bool = True,
              scale: float | None = None) -> ObjectMesh:
    """Load a textured mesh (glTF/GLB, OBJ, PLY, ... anything trimesh reads).

    A BOP model (``obj_000005.ply`` in a folder holding ``models_info.json``) is in
    millimetres: without ``scale`` it is read as such (x 0.001) and checked against the
    ``diameter`` of ``models_info.json`` (:mod:`evtrack.datasets.bop`).

    Args:
        path: mesh file. Scenes with several parts are merged into one mesh.
        name: object name; default: the file stem without ``_textured``.
        recenter: shift the object frame to the bounding-box centre.
        scale: multiply coordinates (e.g. 0.001 for a mesh in millimetres); default 0.001
            for a BOP model, else 1 (metres).

    Raises:
        MeshFileError: missing, unreadable or empty file, or a size outside 5 mm - 3 m (wrong
            units; use ``scale``).
        EventFileError: a BOP model whose size disagrees with its ``models_info.json``.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshFileError(path, "mesh file not found")
    bop_model = False
    if scale is None:
        from evtrack.datasets.bop import MM, is_bop_model_file

        bop_model = is_bop_model_file(path)
        scale = MM if bop_model else 1.0
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise MeshFileError(path, f"cannot load mesh: {type(exc).__name__}: {exc}") from exc
    if isinstance(loaded, trimesh.Scene):
        if not loaded.geometry:
            raise MeshFileError(path, "the file holds no geometry")
        to_geometry = getattr(loaded, "to_geometry", None)
        mesh = to_geometry() if to_geometry else loaded.dump(concatenate=True)
    else:
        mesh = loaded
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshFileError(path, f"expected a triangle mesh, got {type(mesh).__name__} "
                                  "without faces")
    vertices = np.asarray(mesh.vertices, np.float64) * float(scale)
    if not np.isfinite(vertices).all():
        raise MeshFileError(path, "vertex coordinates contain NaN or infinity")
    size = float((vertices.max(0) - vertices.min(0)).max())
    if not _SIZE_LIMITS_M[0] <= size <= _SIZE_LIMITS_M[1]:
        raise MeshFileError(
            path, f"object size {size:.4g} (after scale={scale}) is outside "
                  f"{_SIZE_LIMITS_M[0]}-{_SIZE_LIMITS_M[1]} m: wrong units? pass scale=")
    if bop_model:
        from evtrack.datasets.bop import check_bop_model_size

        check_bop_model_size(path, vertices)
    offset = (vertices.min(0) + vertices.max(0)) / 2.0 if recenter else np.zeros(3)
    texture, uv, colors = _visual_arrays(mesh)
    normals = np.asarray(mesh.vertex_normals, np.float32)
    stem = path.stem[: -len("_textured")] if path.stem.endswith("_textured") else path.stem
    return ObjectMesh(
        name=name or stem,
        vertices=(vertices - offset).astype(np.float32),
        faces=np.asarray(mesh.faces, np.int32),
        normals=normals,
        uv=uv,
        texture=texture,
        colors=colors,
        source=str(path.resolve()),
        offset=offset,
    )


def _visual_arrays(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(texture uint8, uv float32, linear colour multipliers float32) of a trimesh visual."""
    n = len(mesh.vertices)
    white = np.full((1, 1, 3), 255, np.uint8)
    visual = mesh.visual
    if isinstance(visual, trimesh.visual.TextureVisuals):
        material = visual.material
        image = getattr(material, "baseColorTexture", None)
        if image is None:
            image = getattr(material, "image", None)
        factor = np.ones(3, np.float32)
        base = getattr(material, "baseColorFactor", None)
        if base is not None:  # glTF: linear factor, trimesh stores it as uint8 RGBA
            factor = np.asarray(base, np.float32)[:3] / 255.0
        elif image is None and getattr(material, "main_color", None) is not None:
            factor = _srgb_u8_to_linear(np.asarray(material.main_color[:3], np.uint8))
        colors = np.tile(factor, (n, 1)).astype(np.float32)
        if image is not None and visual.uv is not None and len(visual.uv) == n:
            texture = np.ascontiguousarray(np.asarray(image.convert("RGB"), np.uint8))
            return texture, np.asarray(visual.uv, np.float32), colors
        return white, np.zeros((n, 2), np.float32), colors
    vc = np.asarray(visual.vertex_colors)[:, :3] if visual.kind is not None else None
    if vc is not None and len(vc) == n:
        colors = _srgb_u8_to_linear(vc.astype(np.uint8)).astype(np.float32)
    else:
        colors = np.ones((n, 3), np.float32)
    return white, np.zeros((n, 2), np.float32), colors


# ---------------------------------------------------------------------------- procedural
def make_box(size: tuple[float, float, float] = (0.16, 0.21, 0.07), seed: int = 0,
             name: str = "box") -> ObjectMesh:
    """A printed cardboard box (like 003_cracker_box), centred, ``y`` up, front face ``+z``.

    Each face gets its own printed panel on its own base colour (six hues spread evenly around
    the colour wheel from a seeded start), so that the faces, and hence the box's orientation
    and its cuboid corners, can be told apart even in blurred, low-resolution frames — as on
    real packaging, whose sides rarely repeat the front.

    Args:
        size: (width x, height y, depth z) in metres.
        seed: texture seed.
    """
    rng = np.random.default_rng([seed, 1])
    bases = textures.spread_colors(rng, 6)

    def panel(k: int, pw: int, ph: int, corners: np.ndarray) -> np.ndarray:
        return textures.printed_panel(rng, pw, ph, base=bases[k])

    return _textured_box(size, panel, name, f"procedural:box:seed={seed}")


def make_coded_box(size: tuple[float, float, float] = (0.16, 0.21, 0.07), seed: int = 0,
                   name: str = "coded_box") -> ObjectMesh:
    """A box whose eight corners are colour-coded: the demo's object for the pose network.

    Every face is split into four quadrants; each quadrant is printed on the colour of the
    box corner it touches (eight vivid hues 45° apart, :func:`~evtrack.sim.textures.
    corner_palette`), with hatching and small dark text for events. Each cuboid corner is then
    recognisable from the colour around it alone, which a small keypoint network learns in
    under an hour on a CPU; telling corners apart on ordinary packaging (:func:`make_box`,
    the YCB objects) needs the whole object's appearance and far longer training.

    Args:
        size: (width x, height y, depth z) in metres; the same as :func:`make_box`.
        seed: texture seed (palette order and text).
    """
    rng = np.random.default_rng([seed, 2])
    palette = textures.corner_palette(rng, 8)

    def panel(k: int, pw: int, ph: int, corners: np.ndarray) -> np.ndarray:
        colors = tuple(palette[coded_box_corner_index(c)] for c in corners)
        return textures.corner_coded_panel(rng, pw, ph, colors)

    return _textured_box(size, panel, name, f"procedural:coded_box:seed={seed}")


def coded_box_corner_index(corner: np.ndarray) -> int:
    """Palette index of the box corner with these object coordinates: ``4·[x>0] + 2·[y>0] +
    [z>0]`` (used by :func:`make_coded_box`)."""
    return int(4 * (corner[0] > 0) + 2 * (corner[1] > 0) + (corner[2] > 0))


def _textured_box(size: tuple[float, float, float], panel, name: str,
                  source: str) -> ObjectMesh:
    """A centred box with one texture panel per face from ``panel(face, width_px, height_px,
    corners)``, where ``corners`` (4, 3) are the object coordinates of the panel's top-left,
    top-right, bottom-left and bottom-right corners."""
    sx, sy, sz = (float(s) for s in size)
    cell = _TEXTURE_SIZE // 2
    atlas = np.zeros((2 * cell, 3 * cell, 3), np.uint8)
    ex, ey, ez = np.eye(3)
    # (normal, U axis, V axis, face width along U, face height along V)
    faces_def = [
        (ez, ex, ey, sx, sy), (-ez, -ex, ey, sx, sy), (ex, -ez, ey, sz, sy),
        (-ex, ez, ey, sz, sy), (ey, ex, -ez, sx, sz), (-ey, ex, ez, sx, sz),
    ]
    half = np.array([sx, sy, sz]) / 2.0
    vertices, uvs, normals, faces = [], [], [], []
    for k, (n, U, V, fw, fh) in enumerate(faces_def):
        row, col = divmod(k, 3)
        aspect = fw / fh
        pw, ph = (cell, int(cell / aspect)) if aspect >= 1 else (int(cell * aspect), cell)
        centre = n * np.abs(n @ half)
        # image top is +V (v grows upwards), image left is -U
        corners = np.array([centre + (a - 0.5) * fw * U + (b - 0.5) * fh * V
                            for a, b in ((0, 1), (1, 1), (0, 0), (1, 0))])
        atlas[row * cell:(row + 1) * cell, col * cell:(col + 1) * cell] = cv2.resize(
            panel(k, max(pw, 8), max(ph, 8), corners), (cell, cell),
            interpolation=cv2.INTER_AREA)
        u0, u1 = col / 3.0, (col + 1) / 3.0
        v0, v1 = 1.0 - (row + 1) / 2.0, 1.0 - row / 2.0
        base_index = len(vertices)
        for a, b in ((0, 0), (1, 0), (1, 1), (0, 1)):
            vertices.append(centre + (a - 0.5) * fw * U + (b - 0.5) * fh * V)
            uvs.append((u0 + a * (u1 - u0), v0 + b * (v1 - v0)))
            normals.append(n)
        faces += [(base_index, base_index + 1, base_index + 2),
                  (base_index, base_index + 2, base_index + 3)]
    return _assemble(name, vertices, faces, normals, uvs, atlas, source)


def _revolve(radius: np.ndarray, height: np.ndarray, v_coord: np.ndarray,
             semi_axes: tuple[float, float], segments: int = _SEGMENTS
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Surface of revolution about ``y`` with an elliptical cross-section.

    Args:
        radius: (R,) profile radius (relative, multiplied by ``semi_axes``).
        height: (R,) profile heights, metres.
        v_coord: (R,) texture ``v`` of each profile ring.
        semi_axes: (a_x, a_z) metres at relative radius 1.

    Returns:
        vertices (R*(S+1), 3), faces, normals, uv. The seam column is duplicated so that
        ``u`` runs 0..1; normals are computed on the seamless surface.
    """
    rings, seg = len(radius), segments
    theta = np.linspace(0.0, 2.0 * np.pi, seg + 1)
    ax, az = semi_axes
    x = radius[:, None] * ax * np.sin(theta)[None, :]
    z = radius[:, None] * az * np.cos(theta)[None, :]
    y = np.repeat(height[:, None], seg + 1, axis=1)
    verts = np.stack([x, y, z], -1)  # (R, S+1, 3)
    # seamless copy for normals
    idx = np.arange(rings * seg).reshape(rings, seg)
    quads = [(idx[i, j], idx[i, (j + 1) % seg], idx[i + 1, (j + 1) % seg], idx[i + 1, j])
             for i in range(rings - 1) for j in range(seg)]
    tri = np.array([(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads])
    seamless = trimesh.Trimesh(verts[:, :seg].reshape(-1, 3), tri, process=False)
    nrm = np.asarray(seamless.vertex_normals).reshape(rings, seg, 3)
    nrm = np.concatenate([nrm, nrm[:, :1]], axis=1)
    idx2 = np.arange(rings * (seg + 1)).reshape(rings, seg + 1)
    faces = []
    for i in range(rings - 1):
        for j in range(seg):
            a, b, c, d = idx2[i, j], idx2[i, j + 1], idx2[i + 1, j + 1], idx2[i + 1, j]
            faces += [(a, b, c), (a, c, d)]
    u = np.repeat((theta / (2.0 * np.pi))[None, :], rings, axis=0)
    v = np.repeat(v_coord[:, None], seg + 1, axis=1)
    uv = np.stack([u, v], -1).reshape(-1, 2)
    return verts.reshape(-1, 3), np.array(faces), nrm.reshape(-1, 3), uv


def _cap(y: float, semi_axes: tuple[float, float], r: float, up: bool,
         uv_centre: tuple[float, float], uv_radius: tuple[float, float],
         segments: int = _SEGMENTS):
    """A flat elliptical disc at height ``y`` (a fan), facing ``+y`` if ``up``."""
    theta = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ax, az = semi_axes
    rim = np.stack([r * ax * np.sin(theta), np.full(segments, y), r * az * np.cos(theta)], -1)
    verts = np.vstack([[0.0, y, 0.0], rim])
    uv = np.vstack([uv_centre, np.stack([uv_centre[0] + uv_radius[0] * np.sin(theta),
                                         uv_centre[1] + uv_radius[1] * np.cos(theta)], -1)])
    n = np.tile([0.0, 1.0 if up else -1.0, 0.0], (segments + 1, 1))
    faces = []
    for j in range(segments):
        a, b = 1 + j, 1 + (j + 1) % segments
        faces.append((0, a, b) if up else (0, b, a))
    return verts, np.array(faces), n, uv


def _cap_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """A metal lid: grey with concentric rings and a tab."""
    img = np.full((size, size, 3), 170, np.uint8)
    c = size // 2
    for k in range(1, 7):
        shade = int(rng.integers(90, 230))
        cv2.circle(img, (c, c), int(c * k / 7), (shade,) * 3, max(2, size // 60), cv2.LINE_AA)
    cv2.ellipse(img, (c, int(c * 0.7)), (c // 4, c // 8), 0, 0, 360, (60, 60, 60), -1, cv2.LINE_AA)
    return img


def make_can(radius: float = 0.034, height: float = 0.101, seed: int = 0,
             name: str = "can") -> ObjectMesh:
    """A labelled can (like 005_tomato_soup_can), centred, axis ``y``.

    The texture atlas holds the label in its top three quarters (``v`` in [0.25, 1]) and both
    lids in the bottom quarter.
    """
    rng = np.random.default_rng([seed, 2])
    w, h = 2 * _TEXTURE_SIZE, _TEXTURE_SIZE
    atlas = np.zeros((h, w, 3), np.uint8)
    atlas[: 3 * h // 4] = textures.label_band(rng, w, 3 * h // 4)
    lid = _cap_texture(rng, h // 4)
    atlas[3 * h // 4:, : h // 4] = lid
    atlas[3 * h // 4:, h // 4: h // 2] = lid
    half = height / 2.0
    rings = np.linspace(-half, half, 5)
    side = _revolve(np.ones(5), rings, 0.25 + 0.75 * (rings + half) / height, (radius, radius))
    lid_r = (h / 8) / w, (h / 8) / h
    top = _cap(half, (radius, radius), 1.0, True, ((h / 8) / w, 0.125), lid_r)
    bottom = _cap(-half, (radius, radius), 1.0, False, ((3 * h / 8) / w, 0.125), lid_r)
    return _merge(name, [side, top, bottom], atlas, f"procedural:can:seed={seed}")


def make_bottle(height: float = 0.19, semi_axes: tuple[float, float] = (0.048, 0.033),
                seed: int = 0, name: str = "bottle") -> ObjectMesh:
    """A squeeze bottle with a label and a ribbed cap (like 006_mustard_bottle), axis ``y``.

    Args:
        height: total height, metres.
        semi_axes: half width (x) and half depth (z) of the body, metres.
    """
    rng = np.random.default_rng([seed, 3])
    # relative profile: (radius, height fraction); body, shoulder, neck, cap
    prof = np.array([
        (0.0, 0.0), (0.85, 0.0), (0.97, 0.02), (1.0, 0.05), (1.0, 0.62), (0.93, 0.68),
        (0.6, 0.76), (0.36, 0.80), (0.36, 0.83), (0.3, 0.84), (0.3, 0.99), (0.2, 1.0),
        (0.0, 1.0)])
    r, yf = prof[:, 0], prof[:, 1]
    seg_len = np.hypot(np.diff(r * semi_axes[0]), np.diff(yf * height))
    arc = np.concatenate([[0.0], np.cumsum(seg_len)]) / seg_len.sum()
    tex_h, tex_w = _TEXTURE_SIZE, 2 * _TEXTURE_SIZE
    img = np.empty((tex_h, tex_w, 3), np.uint8)
    body_color = textures.random_color(rng)
    img[:] = body_color
    textures.hatch(img, body_color)
    rows = ((1.0 - arc) * (tex_h - 1)).astype(int)  # v = arc, image row 0 is v = 1
    body0, body1 = rows[4], rows[3]  # the label spans the straight body
    img[body0:body1 + 1] = cv2.resize(textures.label_band(rng, tex_w, max(body1 - body0 + 1, 8)),
                                      (tex_w, body1 - body0 + 1))
    cap_color = textures.random_color(rng)
    cap0 = rows[8]  # profile point 8: where the cap starts
    img[: cap0 + 1] = cap_color
    for k in range(0, tex_w, tex_w // 48):  # ribs on the cap
        cv2.line(img, (k, 0), (k, cap0), tuple(int(c * 0.6) for c in cap_color), tex_w // 200)
    surface = _revolve(r, (yf - 0.5) * height, arc, semi_axes)
    return _merge(name, [surface], img, f"procedural:bottle:seed={seed}")


def _merge(name: str, parts, texture: np.ndarray, source: str) -> ObjectMesh:
    verts, faces, normals, uvs, base = [], [], [], [], 0
    for v, f, n, uv in parts:
        verts.append(v)
        faces.append(np.asarray(f) + base)
        normals.append(n)
        uvs.append(uv)
        base += len(v)
    return _assemble(name, np.vstack(verts), np.vstack(faces), np.vstack(normals),
                     np.vstack(uvs), texture, source)


def _assemble(name, vertices, faces, normals, uvs, texture, source) -> ObjectMesh:
    v = np.asarray(vertices, np.float64)
    offset = (v.min(0) + v.max(0)) / 2.0
    n = np.asarray(normals, np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return ObjectMesh(
        name=name,
        vertices=(v - offset).astype(np.float32),
        faces=np.asarray(faces, np.int32),
        normals=n.astype(np.float32),
        uv=np.asarray(uvs, np.float32),
        texture=np.ascontiguousarray(texture),
        colors=np.ones((len(v), 3), np.float32),
        source=source,
        offset=np.zeros(3),
    )


def procedural_object(kind: str, seed: int = 0) -> ObjectMesh:
    """One of :data:`PROCEDURAL_OBJECTS` (``box``, ``coded_box``, ``can``, ``bottle``) with a
    seeded texture."""
    makers = {"box": make_box, "coded_box": make_coded_box, "can": make_can,
              "bottle": make_bottle}
    if kind not in makers:
        raise ConfigError(f"unknown procedural object {kind!r}; choose from {PROCEDURAL_OBJECTS}")
    return makers[kind](seed=seed)


# ---------------------------------------------------------------------------- resolution
def find_ycb_dir(ycb_dir: str | Path | None = None) -> Path | None:
    """The folder holding YCB object folders, or ``None`` if none is found.

    Looks at ``ycb_dir``, then ``$EVTRACK_YCB_DIR``, then ``shared/data/ycb`` and
    ``../shared/data/ycb`` from the working directory and from the source checkout.
    """
    if ycb_dir is not None:
        return Path(ycb_dir) if Path(ycb_dir).is_dir() else None
    candidates = []
    if os.environ.get(_YCB_ENV):
        candidates.append(Path(os.environ[_YCB_ENV]))
    repo = Path(__file__).resolve().parents[2]
    for root in (Path.cwd(), repo):
        candidates += [root / "shared" / "data" / "ycb", root.parent / "shared" / "data" / "ycb"]
    return next((c for c in candidates if c.is_dir()), None)


def _ycb_mesh_file(folder: Path, full: str) -> Path | None:
    for pattern in (f"{full}_textured.gltf", f"{full}_textured.glb", f"{full}.glb",
                    f"{full}.gltf", "textured.obj", "google_16k/textured.obj"):
        p = folder / full / pattern
        if p.is_file():
            return p
    return None


def resolve_object(spec: str, *, seed: int = 0, ycb_dir: str | Path | None = None) -> ObjectMesh:
    """An object by name or path.

    Args:
        spec: a procedural name (``box``, ``coded_box``, ``can``, ``bottle``), a YCB name
            (``003_cracker_box`` or ``cracker_box``), a mesh file path, or a BOP model as
            ``bop:MODELS_DIR:OBJ_ID``. A BOP model file (``.../obj_000005.ply`` beside a
            ``models_info.json``) is read in millimetres (see :func:`load_mesh`).
        seed: texture seed of procedural objects.
        ycb_dir: folder of the YCB meshes (see :func:`find_ycb_dir`).

    Raises:
        ConfigError: an unknown name, a YCB name without a YCB folder, or a BOP spec without
            such a model.
        MeshFileError: an unreadable mesh file.
    """
    if spec in PROCEDURAL_OBJECTS:
        return procedural_object(spec, seed)
    if spec.startswith("bop:"):
        from evtrack.datasets.bop import bop_model_file

        folder, _, obj_id = spec[len("bop:"):].rpartition(":")
        if not folder or not obj_id.isdigit():
            raise ConfigError(f"object {spec!r}: expected bop:MODELS_DIR:OBJ_ID")
        return load_mesh(bop_model_file(folder, int(obj_id)))
    path = Path(spec)
    if path.suffix and (path.is_file() or os.sep in spec or "/" in spec):
        return load_mesh(path)
    matches = [full for full in YCB_OBJECTS if spec in (full, full[4:])]
    if not matches:
        raise ConfigError(
            f"unknown object {spec!r}: give a mesh file, one of {PROCEDURAL_OBJECTS}, or a YCB "
            f"name {YCB_OBJECTS}")
    folder = find_ycb_dir(ycb_dir)
    if folder is None:
        raise ConfigError(
            f"YCB object {spec!r} needs the YCB meshes: pass --ycb-dir or set ${_YCB_ENV} "
            f"(looked in {ycb_dir or 'shared/data/ycb and ../shared/data/ycb'})")
    mesh_file = _ycb_mesh_file(folder, matches[0])
    if mesh_file is None:
        raise MeshFileError(folder / matches[0], "no textured mesh of this YCB object here")
    return load_mesh(mesh_file, name=matches[0])
