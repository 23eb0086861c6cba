"""Overlay video: the object's wireframe at the tracked poses over the RGB frames and the events.

One video frame per RGB frame. On it: the RGB image, the events of the frame interval
(``(t_previous_frame, t_frame]``; positive red, negative blue), the wireframe of the object at
each trajectory's pose at the frame time (one colour per trajectory, white = ground truth) and a
legend. When the RGB and event cameras differ (intrinsics or extrinsic), the events and their
wireframes go in a second panel beside the RGB one.

Wireframe: the mesh's sharp edges (dihedral angle above ``SHARP_EDGE_DEG``) and open borders
(trimesh); when there are too few or too many of them, the edges of the object's bounding box.

The MP4 (H.264 through imageio-ffmpeg) is written to a temporary file and renamed at the end.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.tracking.trajectory import Trajectory

__all__ = ["wireframe_segments", "cuboid_segments", "project_segments", "draw_segments",
           "write_overlay_video", "SHARP_EDGE_DEG", "MAX_EDGES"]

SHARP_EDGE_DEG = 30.0
"""Mesh edges between faces at more than this angle are drawn."""
MAX_EDGES = 1500
"""More sharp edges than this (a finely curved mesh): draw the bounding box instead."""
MIN_VIDEO_WIDTH = 480
"""Small images are enlarged by an integer factor to at least this width (pixels)."""
POSE_TOLERANCE_US = 20_000
"""A trajectory sample up to this long before a frame still gives that frame's pose."""
GROUND_TRUTH_COLOR = (255, 255, 255)
POSITIVE_COLOR = (255, 60, 60)
NEGATIVE_COLOR = (60, 140, 255)
PALETTE = ((255, 200, 0), (0, 230, 120), (255, 0, 255), (0, 220, 255), (255, 120, 0),
           (170, 120, 255), (255, 255, 0))


def cuboid_segments(vertices: np.ndarray) -> np.ndarray:
    """(12, 2, 3) edges of the axis-aligned bounding box of ``vertices`` (object frame, m)."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    corners = np.array([[hi[0] if i & 1 else lo[0], hi[1] if i & 2 else lo[1],
                         hi[2] if i & 4 else lo[2]] for i in range(8)])
    pairs = [(a, a | bit) for a in range(8) for bit in (1, 2, 4) if not a & bit]
    return np.stack([corners[[a, b]] for a, b in pairs])


def wireframe_segments(vertices: np.ndarray, faces: np.ndarray,
                       sharp_deg: float = SHARP_EDGE_DEG, max_edges: int = MAX_EDGES
                       ) -> np.ndarray:
    """(E, 2, 3) object-frame segments outlining a mesh (see the module docstring)."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                           process=True)  # merges the duplicated vertices of UV seams
    sharp = mesh.face_adjacency_edges[mesh.face_adjacency_angles > math.radians(sharp_deg)]
    edges, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    edges = np.concatenate([sharp.reshape(-1, 2), edges[counts == 1]])
    if not 4 <= len(edges) <= max_edges:
        return cuboid_segments(mesh.vertices)
    return mesh.vertices[edges]


def project_segments(segments: np.ndarray, pose: np.ndarray, camera: PinholeCamera
                     ) -> np.ndarray:
    """Object-frame segments (E, 2, 3) at ``pose`` (4, 4) -> pixels (E', 2, 2).

    Segments with an end within 1 cm of the camera plane or behind it are dropped.
    """
    pose = np.asarray(pose, np.float64)
    P = segments.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
    front = (P[:, 2] > 0.01).reshape(-1, 2).all(1)
    uv = camera.project(torch.from_numpy(P)).numpy().reshape(-1, 2, 2)
    ok = front & np.isfinite(uv).reshape(-1, 4).all(1)
    return uv[ok]


def draw_segments(image: np.ndarray, uv: np.ndarray, color: tuple[int, int, int],
                  scale: int, thickness: int = 1) -> None:
    """Draw pixel segments (E, 2, 2) of the native image on ``image`` enlarged by ``scale``
    (in place, anti-aliased, sub-pixel)."""
    shift = 4
    pts = np.round((uv + 0.5) * scale * (1 << shift) - 0.5 * (1 << shift)).astype(np.int64)
    limit = 1 << 28  # keep far-off projections inside OpenCV's integer range
    pts = np.clip(pts, -limit, limit)
    for (x0, y0), (x1, y1) in pts:
        cv2.line(image, (int(x0), int(y0)), (int(x1), int(y1)), color, thickness, cv2.LINE_AA,
                 shift)


def _event_layer(x: np.ndarray, y: np.ndarray, p: np.ndarray, size: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) colours and (H, W) mask of the events (the last event of a pixel wins)."""
    w, h = size
    layer = np.zeros((h, w, 3), np.uint8)
    mask = np.zeros((h, w), bool)
    colors = np.where((p > 0)[:, None], POSITIVE_COLOR, NEGATIVE_COLOR).astype(np.uint8)
    layer[y, x] = colors
    mask[y, x] = True
    return layer, mask


def _enlarge(image: np.ndarray, scale: int) -> np.ndarray:
    if scale == 1:
        return image.copy()
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)


def _pose_index(t_us: np.ndarray, t: int) -> int | None:
    i = int(np.searchsorted(t_us, t, side="right")) - 1
    if i < 0 or t - int(t_us[i]) > POSE_TOLERANCE_US:
        return None
    return i


def _legend(image: np.ndarray, lines: list[tuple[str, tuple[int, int, int]]],
            font_scale: float) -> None:
    y = int(16 * font_scale / 0.45)
    for text, color in lines:
        cv2.putText(image, text, (6, y), cv2.FONT_HERSHEY_SIMPLEX, font_scale, (0, 0, 0), 3,
                    cv2.LINE_AA)
        cv2.putText(image, text, (6, y), cv2.FONT_HERSHEY_SIMPLEX, font_scale, color, 1,
                    cv2.LINE_AA)
        y += int(15 * font_scale / 0.45)


def _even(image: np.ndarray) -> np.ndarray:
    """Pad to even width and height (H.264 with yuv420p needs them)."""
    h, w = image.shape[:2]
    return np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)))


def write_overlay_video(sequence, trajectories: Mapping[str, Trajectory], path: str | Path,
                        *, ground_truth: bool = True, slowdown: float = 4.0,
                        scale: int | None = None, max_frames: int | None = None,
                        progress: bool = False) -> int:
    """Write the overlay video of ``trajectories`` on ``sequence`` (see the module docstring).

    Args:
        sequence: an :class:`~evtrack.Sequence` with RGB frames and an object mesh.
        trajectories: label -> trajectory (object-to-event-camera poses).
        path: the ``.mp4`` to write.
        ground_truth: also draw the ground-truth pose (if the sequence has it).
        slowdown: the video plays this many times slower than real time (its frame rate is
            the RGB rate / ``slowdown``).
        scale: integer enlargement of the images (default: the smallest making them at least
            :data:`MIN_VIDEO_WIDTH` pixels wide).
        max_frames: stop after this many RGB frames.
        progress: show a tqdm bar.

    Returns:
        The number of video frames written.

    Raises:
        ConfigError: no RGB frames, or no mesh.
    """
    import imageio.v2 as imageio
    from tqdm import tqdm

    from evtrack.errors import ConfigError
    from evtrack.sim.objects import load_mesh
    from evtrack.utils import atomic_path

    n = sequence.num_rgb if max_frames is None else min(sequence.num_rgb, int(max_frames))
    where = sequence.root or sequence.meta.name
    if n == 0:
        raise ConfigError(f"{where}: the sequence has no RGB frames to draw on")
    if sequence.mesh_file is None:
        raise ConfigError(f"{where}: the sequence names no object mesh (meta.yaml object.mesh)")
    if not slowdown > 0:
        raise ConfigError(f"video slowdown must be > 0, got {slowdown}")
    mesh = load_mesh(sequence.mesh_file, recenter=False)
    segments = wireframe_segments(mesh.vertices, mesh.faces)
    ev_cam = sequence.meta.event_camera
    rgb_cam = sequence.meta.rgb_camera or ev_cam
    T_rgb_event = torch.linalg.inv(sequence.meta.T_event_rgb).numpy()
    aligned = rgb_cam == ev_cam and np.allclose(T_rgb_event, np.eye(4))
    scale = scale or max(1, math.ceil(MIN_VIDEO_WIDTH / rgb_cam.width))
    font = 0.45 * max(1.0, scale * rgb_cam.width / 640)
    rgb_t = sequence.rgb_times_us.numpy()
    events = sequence.events
    ev_t = events.t.numpy()
    ev_x, ev_y, ev_p = events.x.numpy(), events.y.numpy(), events.p.numpy()
    rate = sequence.meta.rates.get("rgb_hz") or (
        1e6 / float(np.median(np.diff(rgb_t))) if len(rgb_t) > 1 else 30.0)
    tracks = [(label, traj.t_us.numpy(), traj.poses.numpy(), traj.status.numpy(),
               PALETTE[k % len(PALETTE)]) for k, (label, traj) in enumerate(trajectories.items())]
    gt = sequence.ground_truth if ground_truth else None
    legend = [(label, color) for label, *_, color in tracks]
    if gt is not None:
        legend.append(("ground truth", GROUND_TRUTH_COLOR))
    period = int(round(1e6 / rate))
    with atomic_path(path, suffix=".mp4") as tmp:
        writer = imageio.get_writer(tmp, format="FFMPEG", fps=rate / slowdown, codec="libx264",
                                    quality=7, macro_block_size=1, ffmpeg_log_level="error")
        try:
            for i in tqdm(range(n), desc="video", unit="frame", disable=not progress):
                t = int(rgb_t[i])
                t0 = int(rgb_t[i - 1]) if i > 0 else t - period
                a, b = np.searchsorted(ev_t, [t0, t], side="right")
                layer, mask = _event_layer(ev_x[a:b], ev_y[a:b], ev_p[a:b], ev_cam.size)
                poses = []
                for _, t_us, P, status, color in tracks:
                    k = _pose_index(t_us, t)
                    if k is not None and status[k] == 1 and np.isfinite(P[k]).all():
                        poses.append((P[k], color, 2 if len(tracks) == 1 else 1))
                if gt is not None:
                    poses.append((gt.pose_at(t).numpy(), GROUND_TRUTH_COLOR, 1))
                rgb = _enlarge(sequence.rgb(i), scale)
                if aligned:
                    big_mask = _enlarge(mask.astype(np.uint8), scale) > 0
                    rgb[big_mask] = _enlarge(layer, scale)[big_mask]
                    panels = [(rgb, ev_cam, np.eye(4))]
                else:
                    ev_img = np.full_like(layer, 40)
                    ev_img[mask] = layer[mask]
                    panels = [(rgb, rgb_cam, T_rgb_event),
                              (_enlarge(ev_img, scale), ev_cam, np.eye(4))]
                for image, cam, T in panels:
                    for pose, color, thick in poses:
                        uv = project_segments(segments, T @ pose, cam)
                        draw_segments(image, uv, color, scale, thick)
                if len(panels) == 2 and panels[1][0].shape[0] != rgb.shape[0]:
                    ev_big = panels[1][0]
                    h = rgb.shape[0]
                    panels[1] = (cv2.resize(ev_big, (round(ev_big.shape[1] * h / ev_big.shape[0]),
                                                     h), interpolation=cv2.INTER_NEAREST),)
                frame = np.concatenate([pnl[0] for pnl in panels], axis=1)
                _legend(frame, [(f"t = {t * 1e-6:.3f} s", (255, 255, 255)), *legend], font)
                writer.append_data(_even(frame))
        finally:
            writer.close()
    return n
