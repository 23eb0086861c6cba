"""Pictures of optical flow: colour wheel, event frames, arrows (OpenCV drawing).

Conventions: images are (H, W, 3) uint8 RGB; flows are px/s; hue encodes the direction
(0° = +x, image right, turning towards +y, image down) and saturation the speed relative to
``max_speed``.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from evtrack.events import Events
from evtrack.utils import atomic_path

__all__ = ["flow_to_rgb", "color_wheel", "event_frame", "render_flow", "save_png",
           "VideoWriter"]

ARROW_SECONDS = 0.02
"""An arrow shows the displacement over this many seconds (before ``arrow_scale``)."""
NORMAL_COLOR = (255, 200, 0)
FULL_COLOR = (0, 255, 0)


def flow_to_rgb(flow: Tensor | np.ndarray, max_speed: float | None = None) -> np.ndarray:
    """Colour-wheel coding of flows (..., 2) px/s into (..., 3) uint8 RGB; NaN -> black."""
    f = np.asarray(flow.cpu() if isinstance(flow, Tensor) else flow, dtype=np.float32)
    shape = f.shape[:-1]
    f = f.reshape(-1, 2)
    if f.shape[0] == 0:  # no flows (e.g. a frame without RoI flows): OpenCV refuses empty input
        return np.zeros((*shape, 3), dtype=np.uint8)
    bad = ~np.isfinite(f).all(1)
    f = np.where(bad[:, None], 0.0, f)
    mag = np.hypot(f[:, 0], f[:, 1])
    top = float(max_speed) if max_speed else float(mag.max()) if mag.size else 1.0
    top = top if top > 0 else 1.0
    hsv = np.zeros((f.shape[0], 1, 3), dtype=np.uint8)
    hsv[:, 0, 0] = ((np.degrees(np.arctan2(f[:, 1], f[:, 0])) % 360.0) / 2.0).astype(np.uint8)
    hsv[:, 0, 1] = np.clip(mag / top * 255.0, 0, 255).astype(np.uint8)
    hsv[:, 0, 2] = 255
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[:, 0]
    rgb[bad] = 0
    return rgb.reshape(*shape, 3)


def color_wheel(size: int = 64) -> np.ndarray:
    """A (size, size, 3) legend of :func:`flow_to_rgb` (the rim is ``max_speed``)."""
    c = (size - 1) / 2.0
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    f = np.stack([xs - c, ys - c], -1)
    rgb = flow_to_rgb(f, max_speed=c)
    rgb[np.hypot(xs - c, ys - c) > c] = 255
    return rgb


def event_frame(events: Events, sensor_size: tuple[int, int]) -> np.ndarray:
    """Accumulated events as an RGB image: ON in red, OFF in blue, on white."""
    w, h = sensor_size
    img = np.full((h, w, 3), 255, dtype=np.uint8)
    if not len(events):
        return img
    pix = (events.y.to(torch.int64) * w + events.x.to(torch.int64)).cpu()
    on = torch.bincount(pix[events.p.cpu() > 0], minlength=w * h).reshape(h, w).numpy()
    off = torch.bincount(pix[events.p.cpu() < 0], minlength=w * h).reshape(h, w).numpy()
    scale = max(1.0, float(np.percentile(np.maximum(on, off)[np.maximum(on, off) > 0], 95)))
    a_on = np.clip(on / scale, 0, 1)[..., None]
    a_off = np.clip(off / scale, 0, 1)[..., None]
    img = img * (1 - a_on) + np.array([220, 40, 40]) * a_on
    img = img * (1 - a_off) + np.array([40, 80, 220]) * a_off
    return img.astype(np.uint8)


def render_flow(events: Events, xy: Tensor, flow: Tensor, normal: Tensor,
                sensor_size: tuple[int, int], roi_size: int, max_speed: float | None = None,
                arrow_scale: float = 1.0, upscale: int = 2) -> np.ndarray:
    """Side-by-side picture: colour-wheel RoI flow (left), arrows over the events (right).

    Args:
        events: the events of the shown time span.
        xy, flow, normal: (R, 2) RoI centres px, (R, 2) flows px/s, (R,) aperture flags.
        sensor_size: ``(width, height)``.
        roi_size: RoI side in px (the colour patches).
        max_speed: speed of full saturation (default: the largest shown).
        arrow_scale: arrows show ``flow * ARROW_SECONDS * arrow_scale`` px.
        upscale: integer magnification of the output.

    Returns:
        (upscale*H, upscale*2W + legend, 3) uint8 RGB. Normal-flow arrows are drawn in orange.
    """
    w, h = sensor_size
    xy_np = xy.detach().cpu().numpy().reshape(-1, 2)
    fl = flow.detach().cpu().numpy().reshape(-1, 2)
    nm = normal.detach().cpu().numpy().reshape(-1).astype(bool)
    colours = flow_to_rgb(fl, max_speed)
    left = np.zeros((h, w, 3), dtype=np.uint8)
    half = roi_size / 2.0
    for (cx, cy), col in zip(xy_np, colours, strict=True):
        x0, y0 = int(math.floor(cx - half + 0.5)), int(math.floor(cy - half + 0.5))
        left[max(0, y0):min(h, y0 + roi_size), max(0, x0):min(w, x0 + roi_size)] = col
    right = event_frame(events, sensor_size)
    left = cv2.resize(left, (w * upscale, h * upscale), interpolation=cv2.INTER_NEAREST)
    right = cv2.resize(right, (w * upscale, h * upscale), interpolation=cv2.INTER_NEAREST)
    k = ARROW_SECONDS * arrow_scale * upscale
    for (cx, cy), (fx, fy), is_normal in zip(xy_np, fl, nm, strict=True):
        if not (np.isfinite(fx) and np.isfinite(fy)):
            continue
        p0 = (int(round(cx * upscale)), int(round(cy * upscale)))
        p1 = (int(round(cx * upscale + fx * k)), int(round(cy * upscale + fy * k)))
        cv2.arrowedLine(right, p0, p1, NORMAL_COLOR if is_normal else FULL_COLOR, 2,
                        tipLength=0.25)
    wheel = color_wheel(min(96, h * upscale))
    legend = np.full((h * upscale, wheel.shape[1], 3), 255, dtype=np.uint8)
    legend[:wheel.shape[0]] = wheel
    return np.concatenate([left, right, legend], axis=1)


def save_png(path: str | Path, image: np.ndarray) -> None:
    """Write an RGB uint8 image as PNG atomically."""
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{path}: OpenCV could not write the PNG")


class VideoWriter:
    """MP4 writer (imageio-ffmpeg) that leaves the file only when closed successfully.

    Args:
        path: output ``.mp4``.
        fps: frames per second.
    """

    def __init__(self, path: str | Path, fps: float) -> None:
        import imageio.v2 as imageio

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(f".{self.path.name}.tmp.mp4")
        self._writer = imageio.get_writer(self._tmp, fps=fps, codec="libx264",
                                          macro_block_size=1, quality=7)
        self.frames = 0

    def write(self, image: np.ndarray) -> None:
        h, w = image.shape[:2]
        self._writer.append_data(np.ascontiguousarray(image[: h - h % 2, : w - w % 2]))
        self.frames += 1

    def close(self) -> None:
        self._writer.close()
        self._tmp.replace(self.path)

    def abort(self) -> None:
        try:
            self._writer.close()
        finally:
            self._tmp.unlink(missing_ok=True)
