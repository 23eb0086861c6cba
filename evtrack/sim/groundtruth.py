"""Ground truth from the true motion: optical flow at pixels and events, pixel-speed statistics.

Flow definition: the flow at pixel ``(u, v)`` and time ``t`` is ``d/dt`` of the projection of
the 3-D point seen there, ``P = unproject(u, v, z)``, moving with the object's twist:
``Ṗ = v_o + ω × P`` (camera frame, the package's convention). With ``x = X/Z, y = Y/Z``::

    u̇ = fx (Ẋ Z - X Ż) / Z²,   v̇ = fy (Ẏ Z - Y Ż) / Z².

For an event at pixel ``(x, y)`` between two renders ``a`` and ``b``, the depth is taken from
the render(s) where that pixel shows the object (linear in time when both do); events on
pixels that show the object in neither render get NaN (static scene, or noise).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.sim.trajectory import Trajectory

__all__ = ["point_flow", "event_flow", "labelled_event_flow", "pixel_speeds",
           "speed_percentiles", "plot_speed_cdf"]


def point_flow(uv: np.ndarray, depth: np.ndarray, twist: np.ndarray,
               camera: PinholeCamera) -> np.ndarray:
    """Optical flow (px/s) of the surface points seen at pixels ``uv`` with depth ``z``.

    Args:
        uv: (N, 2) pixel coordinates.
        depth: (N,) z in metres (> 0).
        twist: (6,) or (N, 6) ``[v_o, ω]`` camera frame (m/s, rad/s).
        camera: pinhole camera without distortion.

    Returns:
        (N, 2) float64 px/s.
    """
    if camera.dist is not None:
        raise ConfigError("point_flow needs a pinhole camera without distortion")
    uv = np.asarray(uv, np.float64)
    z = np.asarray(depth, np.float64)
    V = np.broadcast_to(np.asarray(twist, np.float64), (len(uv), 6))
    X = (uv[:, 0] - camera.cx) / camera.fx * z
    Y = (uv[:, 1] - camera.cy) / camera.fy * z
    P = np.stack([X, Y, z], -1)
    Pdot = V[:, :3] + np.cross(V[:, 3:], P)
    du = camera.fx * (Pdot[:, 0] * z - X * Pdot[:, 2]) / z ** 2
    dv = camera.fy * (Pdot[:, 1] * z - Y * Pdot[:, 2]) / z ** 2
    return np.stack([du, dv], -1)


def event_flow(x: np.ndarray, y: np.ndarray, t_us: np.ndarray,
               t_a_us: int, depth_a: np.ndarray, mask_a: np.ndarray,
               t_b_us: int, depth_b: np.ndarray, mask_b: np.ndarray,
               trajectory: Trajectory, camera: PinholeCamera) -> np.ndarray:
    """Ground-truth flow at events between two renders ``a`` (earlier) and ``b``.

    Args:
        x, y: (N,) event pixels.
        t_us: (N,) event times in ``[t_a_us, t_b_us]``.
        depth_a, depth_b: (H, W) rendered z (metres) of both renders.
        mask_a, mask_b: (H, W) bool object masks of both renders.
        trajectory: the true motion (twist evaluated at each event's time).

    Returns:
        (N, 2) float32 px/s; NaN where neither render shows the object at the pixel.
    """
    x = np.asarray(x, np.int64)
    y = np.asarray(y, np.int64)
    out = np.full((len(x), 2), np.nan, np.float32)
    if len(x) == 0:
        return out
    ma, mb = mask_a[y, x], mask_b[y, x]
    za, zb = depth_a[y, x].astype(np.float64), depth_b[y, x].astype(np.float64)
    w = (np.asarray(t_us, np.float64) - t_a_us) / max(t_b_us - t_a_us, 1)
    z = np.where(ma & mb, (1 - w) * za + w * zb, np.where(ma, za, zb))
    on = ma | mb
    if not on.any():
        return out
    # events share few distinct timestamps: evaluate the twist once per timestamp
    t_on = np.asarray(t_us, np.int64)[on]
    if len(t_on) > 1 and (t_on[1:] >= t_on[:-1]).all():  # sorted: no need to sort again
        first = np.concatenate([[True], t_on[1:] != t_on[:-1]])
        t_unique, inverse = t_on[first], np.cumsum(first) - 1
    else:
        t_unique, inverse = np.unique(t_on, return_inverse=True)
    twists = trajectory.twist(t_unique * 1e-6)[inverse]
    uv = np.stack([x[on], y[on]], -1).astype(np.float64)
    out[on] = point_flow(uv, z[on], twists, camera).astype(np.float32)
    return out


def labelled_event_flow(x: np.ndarray, y: np.ndarray, t_us: np.ndarray,
                        t_a_us: int, depth_a: np.ndarray, labels_a: np.ndarray,
                        t_b_us: int, depth_b: np.ndarray, labels_b: np.ndarray,
                        trajectories: list[Trajectory], camera: PinholeCamera
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth flow at events between two renders of several objects, and which object
    each event is on.

    An event's object is the one its pixel shows in the render nearer its time (the other
    render's when the nearer shows none); its depth is interpolated in time where both
    renders show that object, else taken from the one that does. With one object it gives
    :func:`event_flow`'s flow.

    Args:
        x, y, t_us: (N,) event pixels and times in ``[t_a_us, t_b_us]``.
        depth_a, depth_b: (H, W) rendered z (metres).
        labels_a, labels_b: (H, W) int object labels (``k + 1`` for object ``k``, 0 none).
        trajectories: the true motion of each object.

    Returns:
        ``(flow, obj)``: (N, 2) float32 px/s (NaN on no object) and (N,) int16 object index
        (-1 on no object).
    """
    x = np.asarray(x, np.int64)
    y = np.asarray(y, np.int64)
    flow = np.full((len(x), 2), np.nan, np.float32)
    la, lb = labels_a[y, x].astype(np.int64), labels_b[y, x].astype(np.int64)
    w = (np.asarray(t_us, np.float64) - t_a_us) / max(t_b_us - t_a_us, 1)
    near_b = w >= 0.5
    label = np.where(near_b, np.where(lb > 0, lb, la), np.where(la > 0, la, lb))
    for k, trajectory in enumerate(trajectories):
        on = label == k + 1
        if not on.any():
            continue
        ma = labels_a == k + 1
        mb = labels_b == k + 1
        flow[on] = event_flow(x[on], y[on], np.asarray(t_us)[on], t_a_us, depth_a, ma,
                              t_b_us, depth_b, mb, trajectory, camera)
    return flow, (label - 1).astype(np.int16)


def pixel_speeds(trajectory: Trajectory, times_s: np.ndarray, points: np.ndarray,
                 camera: PinholeCamera) -> np.ndarray:
    """Mean image speed (px/s) of object points over time (visibility not considered).

    Args:
        times_s: (T,) seconds.
        points: (M, 3) object-frame points (e.g. a subset of mesh vertices).

    Returns:
        (T,) mean over points of ``|d/dt project(T(t) X)|``.
    """
    poses = trajectory.pose(np.asarray(times_s, np.float64))
    twists = trajectory.twist(np.asarray(times_s, np.float64))
    P = points[None, :, :] @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]
    Pdot = twists[:, None, :3] + np.cross(twists[:, None, 3:], P)
    X, Y, Z = P[..., 0], P[..., 1], P[..., 2]
    du = camera.fx * (Pdot[..., 0] * Z - X * Pdot[..., 2]) / Z ** 2
    dv = camera.fy * (Pdot[..., 1] * Z - Y * Pdot[..., 2]) / Z ** 2
    return np.hypot(du, dv).mean(axis=1)


def speed_percentiles(speeds: np.ndarray, q=(10, 50, 90, 99)) -> dict[str, float]:
    """``{"p10": ..., "p50": ...}`` of pixel speeds (px/s), plus the mean."""
    out = {f"p{int(k)}": float(np.percentile(speeds, k)) for k in q}
    out["mean"] = float(np.mean(speeds))
    return out


def plot_speed_cdf(samples: Mapping[str, np.ndarray], path: str | Path,
                   title: str = "Pixel velocity of the object") -> None:
    """Write a cumulative-percentage plot of pixel speeds (one curve per label) as PNG.

    Like the paper's Fig. "Cumulative percentage distribution of pixel velocity".
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from evtrack.utils import atomic_path

    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    for label, values in samples.items():
        v = np.sort(np.asarray(values, np.float64))
        if v.size == 0:
            continue
        ax.plot(v, 100.0 * np.arange(1, v.size + 1) / v.size, label=label)
    ax.set_xlabel("pixel velocity (px/s)")
    ax.set_ylabel("cumulative percentage (%)")
    ax.set_ylim(0, 100)
    ax.set_xlim(left=0)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(title)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
