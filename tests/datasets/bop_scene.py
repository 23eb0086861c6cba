"""Small BOP folders in the format's exact layout, written for the BOP tests.

``write_models`` writes ``models_info.json`` and ``obj_<id:06d>.ply`` in millimetres (a
box, optionally textured the way the BOP ycbv models are: ``comment TextureFile`` in the PLY
header, per-vertex ``texture_u``/``texture_v``); ``write_scene`` writes ``scene_camera.json``,
``scene_gt.json`` (``cam_t_m2c`` in mm; ``cam_R_m2c`` flat row-major or, as YCB-Ev writes it,
nested 3x3), ``rgb/<im_id:06d>.png`` and ``depth/<im_id:06d>.png`` (uint16, value x
depth_scale = mm).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

K_BOP = np.array([[300.0, 0.0, 79.5], [0.0, 310.0, 59.5], [0.0, 0.0, 1.0]])
SIZE = (160, 120)  # width, height
DEPTH_SCALE = 0.1  # a png value of 10000 is 1000 mm


def pose(rotvec, t_m) -> np.ndarray:
    """(4, 4) float64 from a rotation vector (rad) and a translation (m)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t_m
    return T


def write_models(folder: Path, obj_id: int = 1, size_mm=(40.0, 60.0, 20.0),
                 centre_mm=(5.0, -3.0, 2.0), texture: bool = False,
                 diameter_mm: float | None = None) -> Path:
    """A box of ``size_mm`` centred at ``centre_mm`` (model frame) as ``obj_<id>.ply``, with
    its ``models_info.json`` entry (one discrete and one continuous symmetry)."""
    folder.mkdir(parents=True, exist_ok=True)
    box = trimesh.creation.box(extents=size_mm)
    v = np.asarray(box.vertices) + np.asarray(centre_mm)
    path = folder / f"obj_{obj_id:06d}.ply"
    if texture:
        uv = (v[:, :2] - v[:, :2].min(0)) / np.ptp(v[:, :2], axis=0)
        header = ["ply", "format ascii 1.0", f"comment TextureFile obj_{obj_id:06d}.png",
                  f"element vertex {len(v)}", "property float x", "property float y",
                  "property float z", "property float texture_u", "property float texture_v",
                  f"element face {len(box.faces)}", "property list uchar int vertex_indices",
                  "end_header"]
        body = [f"{a} {b} {c} {u} {w}" for (a, b, c), (u, w) in zip(v, uv, strict=True)]
        body += [f"3 {a} {b} {c}" for a, b, c in box.faces]
        path.write_text("\n".join(header + body) + "\n")
        tex = np.zeros((8, 8, 3), np.uint8)
        tex[..., 2] = 255  # BGR on disk: red
        cv2.imwrite(str(folder / f"obj_{obj_id:06d}.png"), tex)
    else:
        trimesh.Trimesh(v, box.faces, process=False).export(path)
    lo = v.min(0)
    info_path = folder / "models_info.json"
    info = json.loads(info_path.read_text()) if info_path.is_file() else {}
    info[str(obj_id)] = {
        "diameter": float(np.linalg.norm(size_mm)) if diameter_mm is None else diameter_mm,
        "min_x": lo[0], "min_y": lo[1], "min_z": lo[2],
        "size_x": size_mm[0], "size_y": size_mm[1], "size_z": size_mm[2],
        "symmetries_discrete": [[-1, 0, 0, 10.0, 0, -1, 0, -6.0, 0, 0, 1, 0, 0, 0, 0, 1]],
        "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [5.0, -3.0, 0]}],
    }
    info_path.write_text(json.dumps(info))
    return folder


def write_scene(folder: Path, gt: dict[int, list[tuple[int, np.ndarray]]],
                images: dict[int, np.ndarray] | None = None,
                depths_m: dict[int, np.ndarray] | None = None, *, K: np.ndarray = K_BOP,
                depth_scale: float = DEPTH_SCALE, nested_R: bool = False,
                image_ids: list[int] | None = None, seed: int = 0) -> Path:
    """A BOP scene: ``gt`` maps an image id to its ``(obj_id, T_m2c (m))`` instances; images
    default to random colours, depths to 0.8 m with a hole; ``image_ids`` (default: those of
    ``gt``) get a camera and frames."""
    rng = np.random.default_rng(seed)
    ids = sorted(gt) if image_ids is None else sorted(image_ids)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    w, h = SIZE
    cams = {}
    for im_id in ids:
        cams[str(im_id)] = {"cam_K": K.reshape(-1).tolist(), "depth_scale": depth_scale,
                            "cam_R_w2c": np.eye(3).reshape(-1).tolist(),
                            "cam_t_w2c": [10.0, -20.0, 500.0]}
        rgb = (images or {}).get(im_id)
        if rgb is None:
            rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / "rgb" / f"{im_id:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        depth = (depths_m or {}).get(im_id)
        if depth is None:
            depth = np.full((h, w), 0.8, np.float32)
            depth[:5, :5] = 0.0
        png = np.round(np.nan_to_num(depth) * 1000.0 / depth_scale).astype(np.uint16)
        cv2.imwrite(str(folder / "depth" / f"{im_id:06d}.png"), png)
    (folder / "scene_camera.json").write_text(json.dumps(cams))
    entries = {}
    for im_id, instances in gt.items():
        entries[str(im_id)] = [
            {"cam_R_m2c": (T[:3, :3].tolist() if nested_R else T[:3, :3].reshape(-1).tolist()),
             "cam_t_m2c": (T[:3, 3] * 1000.0).tolist(), "obj_id": obj_id}
            for obj_id, T in instances]
    (folder / "scene_gt.json").write_text(json.dumps(entries))
    return folder
