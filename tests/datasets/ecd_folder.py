"""Format-true ECD recording folders for the tests: the dataset's text layout, written here.

A camera (the ECD's shapes/boxes/poster lens) follows a known motion; ``groundtruth.txt``
holds its camera-to-world poses with scalar-last quaternions made by SciPy (so a reader that
took them as scalar-first would fail the tests), ``images.txt`` lists grey PNG frames and
``events.txt`` holds random events inside the sensor.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

#: calib.txt of the ECD's shapes, boxes and poster recordings.
CALIB = ("199.092366542 198.82882047 132.192071378 110.712660011 -0.368436311798 "
         "0.150947243557 -0.000296130534385 -0.000759431726241 0.0")
SIZE = (240, 180)


@dataclass
class CameraMotion:
    """A camera that starts at ``p0`` with orientation ``R0`` (camera-to-world) and moves with
    a constant velocity ``v_body`` (m/s) and angular velocity ``w_body`` (rad/s), both in its
    own frame."""

    p0: np.ndarray
    R0: Rotation
    v_body: np.ndarray
    w_body: np.ndarray

    def pose(self, t: float) -> tuple[np.ndarray, Rotation]:
        """Position (3,) and camera-to-world rotation at ``t`` seconds (exact)."""
        R = self.R0 * Rotation.from_rotvec(self.w_body * t)
        # p(t) = p0 + ∫ R(s) v_body ds, integrated finely (R(s) turns about a fixed body axis)
        s = np.linspace(0.0, t, 401)
        vel = (self.R0 * Rotation.from_rotvec(np.outer(s, self.w_body))).apply(self.v_body)
        p = self.p0 + np.trapezoid(vel, s, axis=0) if t > 0 else self.p0.copy()
        return p, R


def default_motion(w_body=(0.0, 0.8, 0.3), v_body=(0.2, 0.0, -0.05)) -> CameraMotion:
    return CameraMotion(np.array([0.3, -0.2, 1.1]),
                        Rotation.from_euler("xyz", [20.0, -35.0, 110.0], degrees=True),
                        np.asarray(v_body, float), np.asarray(w_body, float))


def write_ecd(folder: Path, *, motion: CameraMotion | None = None, t0: float = 1.0,
              duration: float = 0.1, gt_hz: float = 200.0, frame_hz: float = 40.0,
              frame_size: tuple[int, int] = SIZE, n_events: int = 3000, seed: int = 0,
              groundtruth: bool = True, images: bool = True, motion_txt: str | None = None,
              calib: str = CALIB) -> Path:
    """Write an ECD folder; times run from ``t0`` to ``t0 + duration`` seconds. The first
    event and the first ground-truth pose are both at ``t0``."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    (folder / "calib.txt").write_text(calib + "\n")
    t = np.sort(t0 + rng.uniform(0.0, duration, n_events))
    t[0] = t0
    x = rng.integers(0, frame_size[0], n_events)
    y = rng.integers(0, frame_size[1], n_events)
    p = rng.integers(0, 2, n_events)
    (folder / "events.txt").write_text(
        "".join(f"{a:.9f} {b} {c} {d}\n" for a, b, c, d in zip(t, x, y, p, strict=True)))
    if groundtruth:
        motion = motion or default_motion()
        lines = []
        for tk in t0 + np.arange(0.0, duration + 1e-9, 1.0 / gt_hz):
            pos, R = motion.pose(tk - t0)
            q = R.as_quat(scalar_first=False)  # qx qy qz qw
            lines.append(f"{tk:.9f} " + " ".join(f"{v:.12f}" for v in (*pos, *q)) + "\n")
        (folder / "groundtruth.txt").write_text("".join(lines))
    if images:
        (folder / "images").mkdir(exist_ok=True)
        lines = []
        for k, tk in enumerate(t0 + np.arange(0.0, duration, 1.0 / frame_hz)):
            name = f"images/frame_{k:08d}.png"
            img = ((np.arange(frame_size[0])[None, :] * 3 + k * 10) % 256).astype(np.uint8)
            cv2.imwrite(str(folder / name), np.repeat(img, frame_size[1], axis=0))
            lines.append(f"{tk:.9f} {name}\n")
        (folder / "images.txt").write_text("".join(lines))
    if motion_txt is not None:
        (folder / "motion.txt").write_text(motion_txt + "\n")
    return folder
