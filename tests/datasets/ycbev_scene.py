"""A small YCB-Ev scene in the dataset's exact layout, made from a simulated sequence.

The simulator renders an undistorted camera with the event camera's intrinsics; the scene
writer then records what the real rig would: events at the lens-distorted pixels (encoded
with ``ycbev-toolkit``'s own writer), colour images rendered from the colour camera, depth
seen by the depth camera (not registered), ground truth in the colour camera in millimetres,
and the textured BOP model in millimetres (as YCB-V's: per-vertex texture coordinates and a
``TextureFile`` beside it). The calibration
files are the dataset's real ones (from ``../shared``).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import torch

from evtrack.datasets.depth_registration import register_depth
from evtrack.datasets.ycbev import CALIBRATION_FILES, FRAME_PERIOD_US, read_ycbev_calibration
from evtrack.sequence import Sequence
from evtrack.sim.objects import load_mesh

OBJ_ID = 4  # 005_tomato_soup_can
SCENE = "01"


def simulation_config(calibration_dir: Path, path: Path) -> Path:
    """A simulator config whose camera has the event camera's intrinsics (no distortion)."""
    cam = read_ycbev_calibration(calibration_dir).event_camera
    path.write_text(
        f"camera: {{width: {cam.width}, height: {cam.height}, fx: {cam.fx}, fy: {cam.fy}, "
        f"cx: {cam.cx}, cy: {cam.cy}}}\n")
    return path


def distorted_events(seq: Sequence, calibration_dir: Path) -> tuple[np.ndarray, ...]:
    """The simulated events at the pixels the real, distorting lens puts them on."""
    cam = read_ycbev_calibration(calibration_dir).event_camera
    ev = seq.events
    uv = torch.stack([ev.x, ev.y], -1).to(torch.float64)
    uv_d = torch.round(cam.distort_points(uv)).to(torch.int64).numpy()
    inside = ((uv_d[:, 0] >= 0) & (uv_d[:, 0] < cam.width) & (uv_d[:, 1] >= 0)
              & (uv_d[:, 1] < cam.height))
    t = ev.t.numpy()[inside]
    p01 = (ev.p.numpy()[inside] > 0).astype(np.int32)
    return t, uv_d[inside, 0], uv_d[inside, 1], p01


def write_scene(seq: Sequence, calibration_dir: Path, root: Path) -> Path:
    """Write ``root`` as a YCB-Ev dataset root holding scene ``01``; returns the scene folder."""
    import ycbev

    cal = read_ycbev_calibration(calibration_dir)
    root.mkdir(parents=True)
    for name in (*CALIBRATION_FILES, "camera_d435.json"):
        shutil.copy(calibration_dir / name, root / name)
    scene = root / SCENE
    (scene / "rgb").mkdir(parents=True)
    (scene / "depth").mkdir()
    t, x, y, p = distorted_events(seq, calibration_dir)
    ycbev.write_event_data(root / f"{SCENE}_events.int32.zst", t.astype(np.int32),
                           x.astype(np.int32), y.astype(np.int32), p)
    gt = seq.ground_truth
    T_rgb_event = np.linalg.inv(cal.T_event_rgb)
    T_depth_event = np.linalg.inv(cal.T_rgb_depth) @ T_rgb_event
    K_sim = seq.meta.event_camera.K().numpy()
    scene_gt = {}
    colour = ColourCamera(load_mesh(seq.mesh_file, recenter=False), cal.rgb_camera)
    t_end = int(seq.events.t[-1])
    im_id = 0
    while im_id * FRAME_PERIOD_US + FRAME_PERIOD_US <= t_end:
        t_us = im_id * FRAME_PERIOD_US + FRAME_PERIOD_US
        T_rgb = T_rgb_event @ gt.pose_at(t_us).numpy()
        scene_gt[str(im_id)] = [{"cam_R_m2c": T_rgb[:3, :3].tolist(),
                                 "cam_t_m2c": (T_rgb[:3, 3] * 1000.0).tolist(),
                                 "obj_id": OBJ_ID}]
        cv2.imwrite(str(scene / "rgb" / f"{im_id:06d}.png"),
                    cv2.cvtColor(colour.image(T_rgb), cv2.COLOR_RGB2BGR))
        k = int(torch.argmin((seq.depth_times_us - t_us).abs()))
        seen = register_depth(seq.depth(k), K_sim, cal.K_depth, T_depth_event,
                              cal.rgb_camera.size, splat=2)
        cv2.imwrite(str(scene / "depth" / f"{im_id:06d}.png"),
                    np.round(seen * 1000.0).astype(np.uint16))
        im_id += 1
    colour.release()
    (scene / "scene_gt.json").write_text(json.dumps(scene_gt))
    write_model(seq.mesh_file, root / "ycbv_models" / "models", OBJ_ID)
    return scene


class ColourCamera:
    """The colour camera's images of the object (before a grey background): rendered with its
    own intrinsics (lens distortion left out), as the simulator renders its frames."""

    def __init__(self, mesh, camera) -> None:
        from evtrack.camera import PinholeCamera
        from evtrack.sim.renderer import Renderer

        pinhole = PinholeCamera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                                camera.height)
        self.renderer = Renderer(pinhole)
        self.renderer.set_object(mesh)

    def image(self, T_rgb: np.ndarray) -> np.ndarray:
        from evtrack.sim.frames import linear_to_srgb

        out = self.renderer.render(T_rgb)
        return linear_to_srgb(np.where(out.mask[..., None], out.rgb, 0.3))

    def release(self) -> None:
        self.renderer.release()


def write_model(mesh_file: Path, models_dir: Path, obj_id: int, scale: float = 1000.0) -> None:
    """The mesh as a textured BOP model (``obj_XXXXXX.ply`` in millimetres with
    ``texture_u``/``texture_v`` per vertex and ``comment TextureFile obj_XXXXXX.png``, as the
    YCB-V models) with ``models_info.json``."""
    from evtrack.eval.pose_metrics import object_diameter

    models_dir.mkdir(parents=True)
    mesh = load_mesh(mesh_file, recenter=False)
    vertices = np.asarray(mesh.vertices, np.float64) * scale
    stem = f"obj_{obj_id:06d}"
    cv2.imwrite(str(models_dir / f"{stem}.png"), cv2.cvtColor(mesh.texture, cv2.COLOR_RGB2BGR))
    header = ("ply\nformat ascii 1.0\n"
              f"comment TextureFile {stem}.png\n"
              f"element vertex {len(vertices)}\n"
              + "".join(f"property float {k}\n"
                        for k in ("x", "y", "z", "nx", "ny", "nz", "texture_u", "texture_v"))
              + f"element face {len(mesh.faces)}\nproperty list uchar int vertex_indices\n"
              "end_header\n")
    rows = np.hstack([vertices, mesh.normals, mesh.uv])
    with open(models_dir / f"{stem}.ply", "w") as f:
        f.write(header)
        np.savetxt(f, rows, fmt="%.7g")
        np.savetxt(f, np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]), fmt="%d")
    lo, hi = vertices.min(0), vertices.max(0)
    info = {str(obj_id): {"diameter": object_diameter(vertices),
                          "min_x": lo[0], "min_y": lo[1], "min_z": lo[2],
                          "size_x": hi[0] - lo[0], "size_y": hi[1] - lo[1],
                          "size_z": hi[2] - lo[2]}}
    (models_dir / "models_info.json").write_text(json.dumps(info))
