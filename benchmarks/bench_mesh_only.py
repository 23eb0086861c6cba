"""What tracking from the mesh alone costs: each alignment on its own, and whole runs of the
full method with the shipped pose network and with ``pose_source: model``, side by side.

    python benchmarks/bench_mesh_only.py SEQUENCE [SEQUENCE ...] [--threads N] [--frames K]

For each sequence (a simulated benchmark sequence with a YCB object, e.g. from
``evtrack simulate-benchmark``):

* ``appearance``: :class:`evtrack.models.AppearanceRefiner` on ``--frames`` RGB frames from the
  true pose turned 8° about a random axis (wall time per call, ms, median and 90th
  percentile; and its error after the fit, degrees);
* ``depth icp``: :class:`evtrack.models.DepthRefiner` on the same frames' depth from the same
  poses (ms per call);
* ``track``: :meth:`evtrack.Tracker.track` with ``method: full`` and the object's shipped
  network (``full``), then with ``pose_source: model`` from the true first pose
  (``full-model``): wall time, its ratio to the sequence's duration (real-time factor, lower
  is faster), and the errors against the ground truth.

Everything runs in this process, one after the other, with ``--threads`` torch threads
(default 1), so the rows compare on the same machine and load. The line above the table names
the date, the CPU and the commit.
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation


def _angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    R = A[:3, :3].T @ B[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def alignments(seq, frames: int, rng: np.random.Generator) -> tuple[str, str]:
    """Rows of the per-call costs of the two alignments on ``frames`` frames."""
    from evtrack.models import AppearanceRefiner, DepthRefiner
    from evtrack.sim.objects import load_mesh

    cam = seq.meta.rgb_camera or seq.meta.event_camera
    K = cam.K().numpy()
    look = AppearanceRefiner(load_mesh(seq.mesh_file, recenter=False), cam)
    icp = DepthRefiner.from_mesh(seq.mesh_file)
    T_rgb_event = np.linalg.inv(seq.meta.T_event_rgb.numpy())
    idx = np.linspace(0, seq.num_rgb - 1, frames).round().astype(int)
    look_ms, icp_ms, after = [], [], []
    first = T_rgb_event @ seq.ground_truth.pose_at(int(seq.rgb_times_us[0])).numpy()
    look.refine(first, seq.rgb(0))  # the renderer's start-up, not timed
    for i in idx:
        t = int(seq.rgb_times_us[i])
        truth = T_rgb_event @ seq.ground_truth.pose_at(t).numpy()
        axis = rng.normal(size=3)
        prior = truth.copy()
        prior[:3, :3] = Rotation.from_rotvec(np.radians(8.0) * axis / np.linalg.norm(axis)
                                             ).as_matrix() @ truth[:3, :3]
        rgb = seq.rgb(i)
        k = int(np.argmin(np.abs(seq.depth_times_us.numpy() - t)))
        depth = seq.depth(k)
        t0 = time.perf_counter()
        res = look.refine(prior, rgb)
        look_ms.append(1e3 * (time.perf_counter() - t0))
        after.append(_angle_deg(res.pose, truth) if res.refined else np.nan)
        t0 = time.perf_counter()
        icp.refine(prior, depth, K)
        icp_ms.append(1e3 * (time.perf_counter() - t0))
    look.release()
    refined = np.isfinite(after)
    row = (f"| {seq.meta.name} | appearance | {np.median(look_ms):.0f} / "
           f"{np.quantile(look_ms, 0.9):.0f} | {refined.sum()}/{len(after)} fits, median "
           f"{np.nanmedian(after):.2f}° after (8° before) |")
    row2 = (f"| {seq.meta.name} | depth icp | {np.median(icp_ms):.0f} / "
            f"{np.quantile(icp_ms, 0.9):.0f} | |")
    return row, row2


def tracks(seq, threads: int) -> list[str]:
    """Rows of whole runs: ``full`` with the shipped network, then ``full-model``."""
    from evtrack.eval.metrics import tracking_errors
    from evtrack.eval.pose_setup import PoseSourceSpec, make_pose_source, resolve_weights
    from evtrack.tracking.config import TrackerConfig
    from evtrack.tracking.tracker import Tracker

    duration_s = (int(seq.events.t[-1]) - int(seq.events.t[0])) * 1e-6
    gt = seq.ground_truth
    t0 = int(gt.pose_t_us[0])
    rows = []
    spec = PoseSourceSpec("network")
    weights = resolve_weights(spec, [seq.meta.object_name])
    for name in ("full", "full-model"):
        if name == "full":
            cfg = TrackerConfig(torch_threads=threads)
            source = make_pose_source(spec, seq, weights[seq.meta.object_name], threads=threads)
            start = {}
        else:
            cfg = TrackerConfig(torch_threads=threads, pose_source="model")
            source = None
            start = {"start_pose": gt.pose_at(t0), "start_t_us": t0}
        tracker = Tracker.for_sequence(seq, cfg, source)
        t_start = time.perf_counter()
        traj = tracker.track(seq, **start)
        wall = time.perf_counter() - t_start
        err = tracking_errors(traj, gt)
        rows.append(f"| {seq.meta.name} | track {name} | {wall:.1f} s, real-time factor "
                    f"{wall / duration_s:.2f} | {err.position_rmse_cm:.2f} cm / "
                    f"{err.rotation_rmse_deg:.2f}° |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequences", nargs="+", type=Path, help="simulated sequence folders")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--frames", type=int, default=12,
                        help="frames per sequence for the per-call costs (default 12)")
    args = parser.parse_args()
    from bench_tracker import cpu_model, short_commit

    from evtrack import Sequence

    torch.set_num_threads(args.threads)
    print(f"{datetime.date.today()}, {cpu_model()}, commit {short_commit()}, {args.threads} torch "
          f"thread(s)")
    print()
    print("| sequence | what | ms per call (median / p90), or the run | result |")
    print("|:--|:--|--:|:--|")
    rng = np.random.default_rng(0)
    for path in args.sequences:
        seq = Sequence.load(path)
        for row in (*alignments(seq, args.frames, rng), *tracks(seq, args.threads)):
            print(row, flush=True)


if __name__ == "__main__":
    main()
