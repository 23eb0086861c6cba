"""Benchmark figures (PNG, written atomically): tracking curves and error against pixel speed.

The pixel-velocity CDF is :func:`evtrack.sim.groundtruth.plot_speed_cdf`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evtrack.eval.samples import sample_errors
from evtrack.tracking.trajectory import Trajectory

__all__ = ["SpeedErrors", "plot_tracking_curves", "plot_error_vs_speed", "binned_rmse",
           "euler_degrees"]

GROUND_TRUTH_STYLE = {"color": "black", "linewidth": 1.2, "label": "ground truth"}
MIN_BIN_SAMPLES = 20
"""Bins of the error-vs-speed plot with fewer samples are not drawn."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> Path:
    from evtrack.utils import atomic_path

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    _pyplot().close(fig)
    return Path(path)


def euler_degrees(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) -> (N, 3) extrinsic x-y-z Euler angles in degrees, unwrapped over time.

    Rows with a non-finite pose give NaN and do not break the unwrapping of the others.
    """
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, np.float64)
    out = np.full((len(poses), 3), np.nan)
    ok = np.isfinite(poses).reshape(len(poses), -1).all(1)
    if ok.any():
        ang = Rotation.from_matrix(poses[ok, :3, :3]).as_euler("xyz", degrees=True)
        out[ok] = np.unwrap(ang, period=360.0, axis=0)
    return out


def _tracked_or_nan(traj: Trajectory) -> np.ndarray:
    poses = traj.poses.numpy().copy()
    poses[~traj.tracked.numpy()] = np.nan
    return poses


def plot_tracking_curves(trajectories: Mapping[str, Trajectory], ground_truth,
                         path: str | Path, title: str = "",
                         pixel_speed: tuple[np.ndarray, np.ndarray] | None = None) -> Path:
    """Position and rotation of each trajectory against ground truth, with their errors.

    Rows: position x, y, z (cm); rotation as x-y-z Euler angles (deg); position error (cm),
    rotation error (deg) and, if given, the object's pixel speed (px/s). Samples that are not
    tracked (before the first pose, lost) are left out.

    Args:
        trajectories: label -> trajectory (the event camera frame).
        ground_truth: :class:`~evtrack.sequence.GroundTruth` (``pose_at``).
        path: PNG to write.
        title: figure title.
        pixel_speed: ``(t_us, px/s)`` to draw in the last panel.
    """
    plt = _pyplot()
    fig, axes = plt.subplots(3, 3, figsize=(13, 8.5), dpi=100, sharex=True)
    first = next(iter(trajectories.values()), None)
    if first is not None and len(first):
        t_gt = first.t_us
        gt = ground_truth.pose_at(t_gt).numpy()
        ts = t_gt.numpy() * 1e-6
        for k in range(3):
            axes[0, k].plot(ts, 100 * gt[:, k, 3], **GROUND_TRUTH_STYLE)
        for k, ang in enumerate(euler_degrees(gt).T):
            axes[1, k].plot(ts, ang, **GROUND_TRUTH_STYLE)
    for label, traj in trajectories.items():
        if not len(traj):
            continue
        ts = traj.t_us.numpy() * 1e-6
        poses = _tracked_or_nan(traj)
        for k in range(3):
            axes[0, k].plot(ts, 100 * poses[:, k, 3], linewidth=0.9, label=label)
        for k, ang in enumerate(euler_degrees(poses).T):
            axes[1, k].plot(ts, ang, linewidth=0.9, label=label)
        err = sample_errors(traj, ground_truth)
        axes[2, 0].plot(err.t_us * 1e-6, err.position_cm, linewidth=0.9, label=label)
        axes[2, 1].plot(err.t_us * 1e-6, err.rotation_deg, linewidth=0.9, label=label)
    if pixel_speed is not None:
        axes[2, 2].plot(np.asarray(pixel_speed[0]) * 1e-6, pixel_speed[1], color="gray")
    names = [["x (cm)", "y (cm)", "z (cm)"],
             ["rotation x (deg)", "rotation y (deg)", "rotation z (deg)"],
             ["position error (cm)", "rotation error (deg)", "pixel speed (px/s)"]]
    for r in range(3):
        for c in range(3):
            axes[r, c].set_ylabel(names[r][c])
            axes[r, c].grid(True, alpha=0.3)
    for c in range(3):
        axes[2, c].set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7)
    if title:
        fig.suptitle(title)
    # fixed margins: tight_layout would draw the 9 axes once more (seconds on a busy CPU)
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.06, top=0.94, wspace=0.25, hspace=0.12)
    return _save(fig, path)


@dataclass
class SpeedErrors:
    """Per-sample errors of one run with the object's pixel speed at each sample.

    Attributes:
        speed: (N,) px/s; position_cm, rotation_deg: (N,) errors.
    """

    speed: np.ndarray
    position_cm: np.ndarray
    rotation_deg: np.ndarray


def binned_rmse(speed: np.ndarray, error: np.ndarray, edges: np.ndarray,
                min_samples: int = MIN_BIN_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """RMSE of ``error`` per pixel-speed bin.

    Args:
        speed, error: (N,) samples.
        edges: (B + 1,) increasing bin edges (px/s); the last bin includes its right edge.
        min_samples: bins with fewer samples get NaN.

    Returns:
        ``(centres (B,), rmse (B,))``.
    """
    speed = np.asarray(speed, np.float64)
    error = np.asarray(error, np.float64)
    idx = np.clip(np.searchsorted(edges, speed, side="right") - 1, 0, len(edges) - 2)
    inside = (speed >= edges[0]) & (speed <= edges[-1])
    rmse = np.full(len(edges) - 1, np.nan)
    for b in range(len(edges) - 1):
        sel = inside & (idx == b)
        if sel.sum() >= min_samples:
            rmse[b] = np.sqrt(np.mean(error[sel] ** 2))
    return 0.5 * (edges[1:] + edges[:-1]), rmse


def plot_error_vs_speed(series: Mapping[str, SpeedErrors], path: str | Path, bins: int = 12,
                        title: str = "Tracking error against pixel velocity") -> Path:
    """RMSE of position and rotation per pixel-speed bin, one curve per run (the paper's Fig.
    "Tracking performance over pixel velocity").

    Args:
        series: run label -> its samples pooled over the sequences.
        path: PNG to write.
        bins: number of equal-width bins from 0 to the largest speed.
    """
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), dpi=100)
    speeds = [s.speed for s in series.values() if len(s.speed)]
    top = max((float(np.max(s)) for s in speeds), default=1.0)
    edges = np.linspace(0.0, max(top, 1e-9), bins + 1)
    for label, s in series.items():
        for ax, err in zip(axes, (s.position_cm, s.rotation_deg), strict=True):
            x, y = binned_rmse(s.speed, err, edges)
            ax.plot(x, y, marker="o", markersize=3, label=label)
    axes[0].set_ylabel("position RMSE (cm)")
    axes[1].set_ylabel("rotation RMSE (deg)")
    for ax in axes:
        ax.set_xlabel("pixel velocity (px/s)")
        ax.grid(True, alpha=0.3)
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0)
    axes[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)
