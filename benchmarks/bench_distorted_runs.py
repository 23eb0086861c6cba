"""The tracker with a distorted event camera: its velocity steps step by step against the
filters' compiled step runs (``Tracker.step_runs``), side by side in one process.

    python benchmarks/bench_distorted_runs.py [--sequence DIR] [--size 320x240]
        [--duration 1.0] [--dist -0.25 0.08 0.0005 -0.0005 0] [--repeats 3] [--threads 2]

The sequence (simulated when ``--sequence`` is not given: the procedural box, preset
``faster``) is a pinhole camera's; its events are moved to the pixels a camera with the
OpenCV distortion ``--dist`` (``k1 k2 p1 p2 [k3 ...]``) would have seen them at (rounded,
those falling outside the image dropped), and the tracker is given that distorted event camera
with the sequence's own RGB-D camera (pinhole), whose depth frames it carries into the
distorted image. The same sequence with its pinhole event camera runs beside it for scale.

Rows (``mode``): ``compiled`` (the compiled step runs), ``per step`` (``Tracker.step_runs``
off) and, for the distorted camera, ``per step, direct``: per step with the velocity filter's
:class:`~evtrack.filters.interaction.UndistortionTable` taken away, so that every update
undistorts its RoIs anew, as every distorted run did before the compiled runs took distorted
cameras (they declined them, and no table kept the undistortion).

Each setting is tracked once untimed (numba's kernels loaded), then ``--repeats`` rounds of one
timed run per setting, interleaved so that the machine's load drifts over all alike. Oracle
poses (1 cm / 0.03 rad noise), as in ``benchmarks/bench_tracker.py``. Printed per setting: the
median processing time (s) and real-time factor, the velocity and pose stages' time (s; a
compiled run counts its steps' view checks in ``pose``, the step loop outside the stages; a
view check is one compiled call where the object's bounding box projects inside the camera's
view rectangle, :func:`~evtrack.tracking.silhouette.ideal_view_rectangle`, with or without
distortion, and otherwise the silhouette projected through the lens), the
share of the velocity steps done in compiled runs, the position / rotation RMSE against ground
truth (cm / deg) and the largest difference of the outputs from the ``per step`` run of the
same camera (pose entries, twist entries).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from evtrack import Sequence, Tracker, TrackerConfig
from evtrack.camera import PinholeCamera
from evtrack.eval.metrics import tracking_errors
from evtrack.events import Events
from evtrack.tracking.pose_sources import OraclePoseSource
from evtrack.tracking.trajectory import Trajectory

ORACLE_NOISE = {"std_translation": 0.01, "std_rotation": 0.03}
DEFAULT_DIST = [-0.25, 0.08, 5e-4, -5e-4, 0.0]


def simulate(size: tuple[int, int], duration: float, folder: Path) -> Path:
    """A simulated sequence of the procedural box (preset ``faster``) into ``folder/seq``."""
    from evtrack.sim.config import GroundTruthConfig, SimConfig, TrajectoryConfig
    from evtrack.sim.engine import simulate as run_sim
    from evtrack.sim.objects import procedural_object

    cfg = SimConfig(duration=duration, seed=1, trajectory=TrajectoryConfig(preset="faster"),
                    ground_truth=GroundTruthConfig(event_flow=False))
    cfg = dataclasses.replace(cfg, camera=cfg.camera.resized(*size))
    t0 = time.perf_counter()
    stats = run_sim(procedural_object("box", 0), cfg, folder / "seq")
    print(f"simulated {size[0]}x{size[1]}, {duration} s: {stats.num_events} events "
          f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    return folder / "seq"


def distorted_events(events: Events, camera: PinholeCamera) -> Events:
    """``events`` of an ideal pinhole camera at the pixels ``camera`` (the same intrinsics,
    with distortion) sees them at: rounded, outside the image dropped, order kept."""
    uv = torch.stack([events.x, events.y], 1).to(torch.float64)
    d = torch.round(camera.distort_points(uv)).to(torch.int64)
    x, y = d[:, 0], d[:, 1]
    keep = (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
    return Events(x[keep].to(torch.int16), y[keep].to(torch.int16), events.t[keep],
                  events.p[keep], camera.size)


def track(seq: Sequence, camera: PinholeCamera, rgb_camera: PinholeCamera, runs: bool,
          threads: int, table: bool = True) -> tuple[Trajectory, Tracker, float, int]:
    """One run: the trajectory, the tracker, the processing time (s) and the velocity steps
    done in compiled runs. ``table=False``: without the velocity filter's undistortion
    table."""
    cfg = TrackerConfig.from_dict({"method": "full", "torch_threads": threads})
    source = OraclePoseSource.from_sequence(seq, seed=0, **ORACLE_NOISE)
    tracker = Tracker(cfg, camera=camera, mesh=seq.mesh_file, pose_source=source,
                      rgb_camera=rgb_camera, T_event_rgb=seq.meta.T_event_rgb)
    tracker.step_runs = runs
    if not table:
        tracker.motion.vkf._undistortion = None  # every update undistorts its RoIs anew
    in_runs = [0]
    step_run = tracker.scheduler.step_run

    def counted(t0, k, end, poly, pose):
        done = step_run(t0, k, end, poly, pose)
        in_runs[0] += 0 if done is None else done - k
        return done

    tracker.scheduler.step_run = counted
    t0 = time.perf_counter()
    traj = tracker.track(seq)
    return traj, tracker, time.perf_counter() - t0, in_runs[0]


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, help="a sequence folder (default: simulate one)")
    ap.add_argument("--size", default="320x240", help="simulated image size WxH")
    ap.add_argument("--duration", type=float, default=1.0, help="simulated seconds")
    ap.add_argument("--dist", type=float, nargs="+", default=DEFAULT_DIST,
                    help="OpenCV distortion k1 k2 p1 p2 [k3 [k4 k5 k6]]")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per setting")
    ap.add_argument("--threads", type=int, default=2, help="torch (and kernel) threads")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.repeats < 1 or args.threads < 1:
        _parser().error("--repeats and --threads must be >= 1")
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.sequence
        if folder is None:
            w, h = (int(v) for v in args.size.lower().split("x"))
            folder = simulate((w, h), args.duration, Path(tmp))
        return _compare(args, folder)


def _compare(args: argparse.Namespace, folder: Path) -> int:
    pinhole_seq = Sequence.load(folder)
    pinhole = pinhole_seq.meta.event_camera
    rgb_camera = pinhole_seq.meta.rgb_camera or pinhole
    distorted = PinholeCamera(pinhole.fx, pinhole.fy, pinhole.cx, pinhole.cy, pinhole.width,
                              pinhole.height, dist=args.dist)
    warped = distorted_events(pinhole_seq.events, distorted)
    distorted_seq = Sequence.load(folder)
    distorted_seq.iter_events = lambda window_us=None, count=None: warped.windows(
        duration_us=window_us, count=count)
    print(f"{folder}: {len(pinhole_seq.events)} events, {len(warped)} inside the distorted "
          f"image; dist {args.dist}; {args.threads} threads, {torch.get_num_threads()} torch "
          "threads before the runs", file=sys.stderr)
    settings = {("distorted", "per step, direct"): (distorted_seq, distorted, False, False)}
    for cam, seq, camera in (("distorted", distorted_seq, distorted),
                             ("pinhole", pinhole_seq, pinhole)):
        settings[(cam, "per step")] = (seq, camera, False, True)
        settings[(cam, "compiled")] = (seq, camera, True, True)
    for seq, camera, runs, table in settings.values():  # untimed: numba's kernels loaded
        track(seq, camera, rgb_camera, runs, args.threads, table)
    times: dict[tuple[str, str], list[float]] = {key: [] for key in settings}
    last: dict[tuple[str, str], tuple[Trajectory, Tracker, int]] = {}
    for _ in range(args.repeats):
        for key, (seq, camera, runs, table) in settings.items():
            traj, tracker, wall, in_runs = track(seq, camera, rgb_camera, runs, args.threads,
                                                 table)
            times[key].append(wall)
            last[key] = (traj, tracker, in_runs)
    _print_table(times, last, pinhole_seq)
    return 0


def _print_table(times: dict, last: dict, seq: Sequence) -> None:
    line = (f"{'camera':<10} {'mode':<17} {'proc s':>7} {'rtf':>6} {'velocity s':>10} "
            f"{'pose s':>7} {'in runs':>8} {'cm / deg':>12} {'max |Δ| pose, twist':>22}  runs (s)")
    print(line)
    print("-" * len(line))
    for (cam, mode), walls in times.items():
        traj, tracker, in_runs = last[(cam, mode)]
        ref = last[(cam, "per step")][0]
        span = (int(traj.t_us[-1]) - int(traj.t_us[0])) * 1e-6
        wall = statistics.median(walls)
        st = tracker.stats
        err = tracking_errors(traj, seq.ground_truth)
        d_pose = float((traj.poses.nan_to_num(7.0) - ref.poses.nan_to_num(7.0)).abs().max())
        d_twist = float((traj.twists - ref.twists).abs().max())
        print(f"{cam:<10} {mode:<17} {wall:>7.2f} "
              f"{wall / span:>6.2f} {st.time_s.get('velocity', 0.0):>10.2f} "
              f"{st.time_s.get('pose', 0.0):>7.2f} {in_runs / max(st.steps, 1):>8.0%} "
              f"{err.position_rmse_cm:>5.2f} / {err.rotation_rmse_deg:>5.2f} "
              f"{d_pose:>10.1e}, {d_twist:>9.1e}  " + " ".join(f"{w:.2f}" for w in walls),
              flush=True)


if __name__ == "__main__":
    sys.exit(main())
