"""evtrack's motion estimates on real event recordings, against their ground truth.

    python benchmarks/bench_real.py [--data DIR] [--plane-depth M]

Reads every ECD recording of ``../shared/data/real`` (the folder beside the repository; see
its README.md; ``--data`` to read another), imports each into a sequence folder with
:func:`evtrack.datasets.ecd.import_ecd` (the static scene as the tracked object: a plane
facing the first camera pose at ``--plane-depth``, default the importer's 1 m) and prints one
table. Nothing is tuned here: both estimators run at their defaults.

Estimators, side by side in the same run:

* ``tracker``: :class:`evtrack.Tracker` at its default config but ``method: velocity`` (the
  ``full`` method needs a pose source: a network or ground truth; ``velocity`` takes a start
  pose and then events only), started with ``reset(start_pose, start_t_us)`` from the
  imported ``meta.yaml`` (the plane facing the camera at the first event). Its RoI depth is
  the default ``sensor`` source; with no depth frames every RoI takes the fallback, the
  predicted depth of the object's origin: the plane's depth.
* ``flow+kf``: the library's parts at generic settings: :class:`evtrack.flow.TripletFlow`
  (``FlowConfig()``, 2 ms windows) and :class:`evtrack.filters.VelocityKF`
  (``VelocityKFConfig()``), one predict + update per flow window with every RoI of the window
  at a constant depth of 0.7 m (a window without RoIs only predicts).

Both give a twist ``[v_o, ω]`` of the scene relative to the camera (camera frame) per step (the
tracker: 1 ms; ``flow+kf``: per 2 ms window). Each is compared over the **second half** of
the recording (the filters start from rest):

* rotation samples (``motion.txt``: the camera's angular velocity ``w`` from the DAVIS IMU,
  rad/s): the reference is ``-w``, since a camera turning with ``w`` sees the static scene turn
  with ``-w`` (``dP/dt = -w × P`` for a scene point ``P`` in the camera frame). ``cos`` and
  ``ratio`` compare the mean ``ω`` with ``-w`` (cosine of the angle, ``|mean| / |w|``); ``RMSE``
  is over the steps, ``sqrt(mean |ω_k + w|²)`` in rad/s. ``target``: whether the row meets
  the tracker's target on these samples, cosine >= 0.9 and ratio in [0.8, 1.25]
  (``met``/``missed``); a last line counts the tracker's rows that meet it.
* the slider (``groundtruth.txt``: camera poses): the reference is the ground-truth twist of
  the scene (``v_o`` ≈ (-0.307, 0, 0) m/s: the camera slides along its ``+x``, ``ω`` = 0) at
  each step's time. ``cos``/``ratio`` compare mean ``v_o`` with the mean ground-truth
  ``v_o``; ``RMSE`` is over the steps (m/s; for ``ω``, rad/s against 0). The tracker's pose
  at its last step is compared with the ground-truth pose there (position error in mm,
  rotation error in degrees). The scene is at 0.5-2.4 m (its SOURCE.md), not one plane, so
  the translation's scale follows whatever depth each estimator assumes.

The sign of ``-w`` is checked on the data itself, without any flow method (the ``sign check``
lines after the table): the events of each rotation sample are warped to its first event's
time by the rotational flow of a candidate ``ω`` (ideal pinhole pixels, lens distortion
undone) and accumulated into an image; the warp that matches the motion gives the sharpest
image (the largest variance: contrast maximisation). On all four samples ``ω = -w`` gives the
sharpest image and ``+w`` the blurriest, with no warp between them, e.g. for ``shapes``
variances 4.39 (-w), 1.74 (none), 1.04 (+w). The samples' ``flow.npy`` (from the carrying
repository) is the pinhole rotational flow of ``-w`` as a displacement in pixels over the
sample's duration (not px/s), so it agrees with ``-w`` too, but it was made from
``motion.txt`` and is not used here.

Without the data folder the script says so and exits 0. It runs in about 20 s on 2 cores.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "real"
FLOW_KF_DEPTH_M = 0.7  # the constant depth of the flow+kf rows
TARGET_MIN_COS = 0.9  # the target on the rotation samples: cosine at least this
TARGET_RATIO = (0.8, 1.25)  # ... and the magnitude ratio within this range


@dataclass
class Estimate:
    """One estimator's twists over a recording: ``t_us`` (N,), ``twists`` (N, 6), and for the
    tracker its last pose (4, 4) and time."""

    method: str
    t_us: np.ndarray
    twists: np.ndarray
    last_pose: np.ndarray | None = None
    last_t_us: int | None = None


# ---------------------------------------------------------------------------- estimators
def track_velocity(seq) -> Estimate:
    """``evtrack.Tracker`` (default config, ``method: velocity``) from the imported start pose."""
    from evtrack import Tracker
    from evtrack.tracking.config import TrackerConfig

    tracker = Tracker.for_sequence(seq, TrackerConfig(method="velocity"))
    extra = seq.meta.extra
    tracker.reset(np.asarray(extra["start_pose"], np.float64), t_us=int(extra["start_t_us"]))
    for chunk in seq.iter_events(window_us=50_000):
        tracker.push_events(chunk)
    tracker.flush()
    traj = tracker.trajectory()
    tracking = traj.status.numpy() == 1
    t = traj.t_us.numpy()[tracking]
    return Estimate("tracker", t, traj.twists.numpy()[tracking],
                    traj.poses.numpy()[tracking][-1] if tracking.any() else None,
                    int(t[-1]) if tracking.any() else None)


def flow_and_kf(seq) -> Estimate:
    """``TripletFlow`` + ``VelocityKF`` at generic settings, one update per flow window."""
    from evtrack.filters import VelocityKF
    from evtrack.flow import FlowConfig, TripletFlow

    cam = seq.meta.event_camera
    events = seq.events
    flow = TripletFlow(FlowConfig(sensor_size=cam.size))
    res = flow(events)
    kf = VelocityKF(cam)
    kf.reset(1)
    window_us = flow.config.window_us
    dt = window_us * 1e-6
    first, last = events.t_start // window_us, events.t_end // window_us
    t_out, twists = [], []
    for w in range(int(first), int(last) + 1):
        rows = res.window == w
        if rows.any():
            uv = res.xy[rows].double()[None]
            depth = torch.full((1, uv.shape[1]), FLOW_KF_DEPTH_M, dtype=torch.float64)
            twist = kf(dt, uv, depth, res.flow[rows].double()[None], res.normal[rows][None])
        else:
            twist = kf.predict(dt)
        t_out.append((w + 1) * window_us)
        twists.append(twist[0].tolist())
    return Estimate("flow+kf", np.asarray(t_out, np.int64), np.asarray(twists))


# ---------------------------------------------------------------------------- metrics
def _second_half(est: Estimate, seq) -> tuple[np.ndarray, np.ndarray]:
    span = seq.meta.extra["event_span_us"]
    keep = est.t_us >= (span[0] + span[1]) / 2.0
    return est.t_us[keep], est.twists[keep]


def _compare(est: np.ndarray, ref: np.ndarray) -> tuple[float, float, float]:
    """``(cos, ratio, RMSE)`` of per-step vectors ``est`` (N, 3) against ``ref`` (N, 3)."""
    if not len(est):
        return math.nan, math.nan, math.nan
    mean, mean_ref = est.mean(0), ref.mean(0)
    n, n_ref = np.linalg.norm(mean), np.linalg.norm(mean_ref)
    cos = float(mean @ mean_ref / (n * n_ref)) if n > 0 and n_ref > 0 else math.nan
    ratio = float(n / n_ref) if n_ref > 0 else math.nan
    rmse = float(np.sqrt(((est - ref) ** 2).sum(1).mean()))
    return cos, ratio, rmse


def _num(x: float, fmt: str) -> str:
    return "-" if math.isnan(x) else format(x, fmt)


def _vec(v: np.ndarray, digits: int = 3) -> str:
    return "(" + ", ".join(f"{x:+.{digits}f}" for x in v) + ")"


def rotation_rows(name: str, seq, estimates: list[Estimate]) -> list[list[str]]:
    """Rows of a rotation sample: each estimator's ω against -w."""
    ref = -np.asarray(seq.meta.extra["imu_angular_velocity"]["w_rad_s"])
    rows = []
    for est in estimates:
        _, tw = _second_half(est, seq)
        omega = tw[:, 3:]
        cos, ratio, rmse = _compare(omega, np.broadcast_to(ref, omega.shape))
        rows.append([name, est.method, "ω rad/s", _vec(ref),
                     _vec(omega.mean(0)) if len(omega) else "-", _num(cos, "+.3f"),
                     _num(ratio, ".3f"), _num(rmse, ".3f"), str(len(omega)),
                     "met" if meets_target(cos, ratio) else "missed"])
    return rows


def meets_target(cos: float, ratio: float) -> bool:
    """Cosine >= :data:`TARGET_MIN_COS` and ratio within :data:`TARGET_RATIO` (NaN: no)."""
    return cos >= TARGET_MIN_COS and TARGET_RATIO[0] <= ratio <= TARGET_RATIO[1]


def slider_rows(name: str, seq, estimates: list[Estimate]) -> list[list[str]]:
    """Rows of a sequence with pose ground truth: v_o and ω against the ground truth, and the
    tracker's last pose."""
    from evtrack.geometry import inverse

    gt = seq.ground_truth
    rows = []
    for est in estimates:
        t, tw = _second_half(est, seq)
        ref = gt.twist_at(torch.as_tensor(t)).numpy() if len(t) else np.zeros((0, 6))
        for part, label in ((slice(0, 3), "v_o m/s"), (slice(3, 6), "ω rad/s")):
            cos, ratio, rmse = _compare(tw[:, part], ref[:, part])
            rows.append([name, est.method, label,
                         _vec(ref[:, part].mean(0)) if len(ref) else "-",
                         _vec(tw[:, part].mean(0)) if len(tw) else "-",
                         _num(cos, "+.3f"), _num(ratio, ".3f"), _num(rmse, ".3f"),
                         str(len(tw)), "-"])
        if est.last_pose is not None:
            T_gt = gt.pose_at(est.last_t_us).numpy()
            D = inverse(torch.from_numpy(T_gt)).numpy() @ est.last_pose
            dpos = np.linalg.norm(est.last_pose[:3, 3] - T_gt[:3, 3]) * 1e3
            dang = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(D[:3, :3]) - 1) / 2))))
            rows.append([name, est.method, "last pose", "ground truth",
                         f"Δp {dpos:.1f} mm, Δθ {dang:.2f}°", "-", "-", "-", "1", "-"])
    return rows


def sign_check(seq) -> str:
    """Image-of-warped-events variance for ω = -w, 0, +w (see the module docstring)."""
    from evtrack.camera import PinholeCamera
    from evtrack.filters import interaction_matrix

    cam = seq.meta.event_camera
    w = np.asarray(seq.meta.extra["imu_angular_velocity"]["w_rad_s"])
    ev = seq.events
    uv = cam.undistort_points(torch.stack([ev.x, ev.y], 1).double())
    pinhole = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    J = interaction_matrix(uv, torch.ones(len(uv), dtype=torch.float64), pinhole)[..., 3:]
    dt = ((ev.t - ev.t[0]).double() * 1e-6).numpy()
    variances = {}
    for label, omega in (("-w", -w), ("none", 0 * w), ("+w", w)):
        warped = uv.numpy() - dt[:, None] * (J @ torch.from_numpy(omega)).numpy()
        x, y = np.round(warped[:, 0]).astype(int), np.round(warped[:, 1]).astype(int)
        inside = (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)
        image = np.zeros((cam.height, cam.width))
        np.add.at(image, (y[inside], x[inside]), 1.0)
        variances[label] = float(image.var())
    best = max(variances, key=variances.get)
    return ", ".join(f"{k} {v:.2f}" for k, v in variances.items()) + f" -> sharpest: {best}"


# ---------------------------------------------------------------------------- main
def _table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    line = "  ".join("-" * w for w in widths)
    out = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)), line]
    out += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    return "\n".join(out)


def run(data: Path, plane_depth: float | None, work: Path) -> int:
    import evtrack
    from evtrack.datasets.ecd import DAVIS240C_SIZE, ecd_sensor_size, import_ecd
    from evtrack.errors import EventFileError

    folders = sorted(p for p in data.iterdir() if (p / "calib.txt").is_file())
    if not folders:
        print(f"skipped: no ECD recording (a folder with calib.txt) in {data}")
        return 0
    rows: list[list[str]] = []
    notes: list[str] = []
    checks: list[str] = []
    for folder in folders:
        has_motion = (folder / "motion.txt").is_file()
        has_poses = (folder / "groundtruth.txt").is_file()
        if not (has_motion or has_poses):
            notes.append(f"{folder.name}: skipped (no motion.txt or groundtruth.txt)")
            continue
        try:
            size = ecd_sensor_size(folder)
        except EventFileError:
            size = DAVIS240C_SIZE
            notes.append(f"{folder.name}: no images.txt; sensor size {size[0]}x{size[1]} "
                         "(the ECD's DAVIS240C)")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = import_ecd(folder, work / folder.name, sensor_size=size,
                             plane_depth=plane_depth)
        notes += [f"{folder.name}: {w.message}" for w in caught]
        seq = evtrack.Sequence.load(out)
        estimates = [track_velocity(seq), flow_and_kf(seq)]
        name = folder.name.removeprefix("ecd_").removesuffix("_rotation_sample")
        if has_motion:
            rows += rotation_rows(name, seq, estimates)
            checks.append(f"{name}: image variance of events warped by ω = " + sign_check(seq))
        if has_poses:
            rows += slider_rows(name, seq, estimates)
        print(f"done {folder.name}", file=sys.stderr)
    depth = seq.meta.extra["scene"]["depth_m"]
    print(f"Real recordings ({data}); tracker: default config, method velocity, plane at "
          f"{depth} m; flow+kf: FlowConfig(), VelocityKFConfig(), depth {FLOW_KF_DEPTH_M} m. "
          "Second half of each recording; reference: -w (rotation samples) or the ground-"
          "truth twist (slider).\n")
    print(_table(rows, ["recording", "method", "quantity", "reference", "estimate (mean)",
                        "cos", "ratio", "RMSE", "n", "target"]))
    print("\nn: samples compared (tracker: 1 ms steps; flow+kf: 2 ms flow windows).")
    targets = [r[-1] for r in rows if r[1] == "tracker" and r[-1] != "-"]
    print(f"target (cos >= {TARGET_MIN_COS}, ratio {TARGET_RATIO[0]}-{TARGET_RATIO[1]}): the "
          f"tracker meets it on {targets.count('met')} of {len(targets)} rotation samples")
    print("\nsign check (contrast of events warped by the rotational flow of ω; the sharpest "
          "image has the largest variance):")
    for line in checks:
        print(f"  {line}")
    print("\nnotes:")
    for line in notes:
        print(f"  {line}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="See the module docstring for what each row measures.")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, metavar="DIR",
                        help=f"folder of ECD recordings (default {DEFAULT_DATA})")
    parser.add_argument("--plane-depth", type=float, default=None, metavar="M",
                        help="depth of the scene plane of the import (default: the importer's, "
                             "1 m)")
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        print(f"skipped: the real recordings are absent (looked for {args.data}; pass "
              "--data DIR)")
        return 0
    with tempfile.TemporaryDirectory(prefix="bench_real-") as tmp:
        return run(args.data, args.plane_depth, Path(tmp))


if __name__ == "__main__":
    sys.exit(main())
