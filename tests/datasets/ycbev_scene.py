"""A small YCB-Ev scene in the dataset's exact layout, made from a simulated sequence.

The simulator renders an undistorted camera with the event camera's intrinsics; the scene
writer then records what the real rig would: events at the lens-distorted pixels (encoded
with ``ycbev-toolkit``'s own writer), depth seen by the depth camera (not registered), ground
truth in the colour camera in millimetres, and the BOP model in millimetres. The calibration
files are the dataset's real ones (from ``../shared``).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh

from evtrack.datasets.depth_registration import register_depth
from evtrack.datasets.ycbev import CALIBRATION_FILES, FRAME_PERIOD_US, read_ycbev_calibration
from evtrack.sequence import Sequence

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
    t_end = int(seq.events.t[-1])
    im_id = 0
    while im_id * FRAME_PERIOD_US + FRAME_PERIOD_US <= t_end:
        t_us = im_id * FRAME_PERIOD_US + FRAME_PERIOD_US
        T_rgb = T_rgb_event @ gt.pose_at(t_us).numpy()
        scene_gt[str(im_id)] = [{"cam_R_m2c": T_rgb[:3, :3].tolist(),
                                 "cam_t_m2c": (T_rgb[:3, 3] * 1000.0).tolist(),
                                 "obj_id": OBJ_ID}]
        k = int(torch.argmin((seq.rgb_times_us - t_us).abs()))
        cv2.imwrite(str(scene / "rgb" / f"{im_id:06d}.png"),
                    cv2.cvtColor(seq.rgb(k), cv2.COLOR_RGB2BGR))
        k = int(torch.argmin((seq.depth_times_us - t_us).abs()))
        seen = register_depth(seq.depth(k), K_sim, cal.K_depth, T_depth_event,
                              cal.rgb_camera.size, splat=2)
        cv2.imwrite(str(scene / "depth" / f"{im_id:06d}.png"),
                    np.round(seen * 1000.0).astype(np.uint16))
        im_id += 1
    (scene / "scene_gt.json").write_text(json.dumps(scene_gt))
    write_model(seq.mesh_file, root / "ycbv_models" / "models", OBJ_ID)
    return scene


def write_model(mesh_file: Path, models_dir: Path, obj_id: int, scale: float = 1000.0) -> None:
    """The mesh as a BOP model (``obj_XXXXXX.ply``, millimetres) with ``models_info.json``."""
    from evtrack.eval.pose_metrics import object_diameter

    models_dir.mkdir(parents=True)
    mesh = trimesh.load(mesh_file, force="mesh", process=False)
    mesh.apply_scale(scale)
    mesh.export(models_dir / f"obj_{obj_id:06d}.ply")
    vertices = np.asarray(mesh.vertices)
    lo, hi = vertices.min(0), vertices.max(0)
    info = {str(obj_id): {"diameter": object_diameter(vertices),
                          "min_x": lo[0], "min_y": lo[1], "min_z": lo[2],
                          "size_x": hi[0] - lo[0], "size_y": hi[1] - lo[1],
                          "size_z": hi[2] - lo[2]}}
    (models_dir / "models_info.json").write_text(json.dumps(info))
