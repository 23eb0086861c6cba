"""Real-time factor and update latency of evtrack.Tracker on CPU.

    python benchmarks/bench_tracker.py [--size 320x240] [--duration 1.0] [--threads 2 1]
                                       [--methods full pose] [--sequence DIR] [--weights W.pt]
                                       [--caps 0 2000 1000] [--search-per-window 0 128 64]
                                       [--pose-async off on] [--pose-prior off on]
                                       [--save-sequence DIR]

Simulates a ``faster`` sequence of the procedural box (or takes ``--sequence``), then tracks it
with each method and thread count in this process, side by side. The pose source is the
oracle (ground truth with 1 cm / 0.03 rad noise) unless ``--weights`` gives pose-network
weights (then the network runs at 5 Hz on the RGB frames, on CPU; an ``.onnx`` file on
onnxruntime with the row's threads, not spinning between calls, as ``evtrack evaluate`` and
``evtrack track`` run it).

Columns:
    rtf: processing time / sequence time (< 1: faster than real time).
    ev/s: events processed per second of processing.
    flow, velocity, pose, frames: seconds per stage (the pose source is included in frames
        when it runs in the caller's thread, ``async off``).
    pose src: seconds in the pose source (in the tracker's worker thread with ``async on``).
    async: ``TrackerConfig.pose_async``; ``--pose-async off on`` compares both.
    prior: ``TrackerConfig.pose_prior`` (the network looks for the object around the track's
        pose first: one crop pass instead of the whole image and a crop); ``--pose-prior off
        on`` compares both.
    group p50/p95: processing time of one step group (``flow_batch_steps`` velocity steps:
        one flow call and the filter steps) — the latency of an output in live use.
    filters/step: mean time of one velocity-filter + pose-filter step (µs).
    cap: ``max_events_per_step`` (events per 1 ms step entering the flow; thinned above it):
        ``--caps`` compares the speed and the error of several budgets.
    sample: ``search_per_roi_window`` (events of a RoI window searched for candidates, a hash
        sample; 0: all): ``--search-per-window`` compares several.
    rt, min bgt, min ev: ``realtime_load`` (0: off), the lowest search budget and the lowest
        event budget per step it set (0: none); ``--realtime-load 0 0.9`` compares the
        deterministic default with live use.

Timings on a shared machine are noisy; rerun when it is quiet.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

# first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.runtime.openmp_wait)
import evtrack  # noqa: F401  # isort: skip
import numpy as np
import torch

from evtrack import Sequence
from evtrack.demo import demo_tracker_config
from evtrack.runtime.openmp_wait import wait_policy
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import NetworkPoseSource, OraclePoseSource
from evtrack.tracking.tracker import Tracker


def _simulate(size: tuple[int, int], duration: float, folder: Path) -> Sequence:
    from evtrack.sim.config import GroundTruthConfig, SimConfig, TrajectoryConfig
    from evtrack.sim.engine import simulate
    from evtrack.sim.objects import procedural_object

    cfg = SimConfig(duration=duration, seed=1, trajectory=TrajectoryConfig(preset="faster"),
                    ground_truth=GroundTruthConfig(event_flow=False))
    cfg = dataclasses.replace(cfg, camera=cfg.camera.resized(*size))
    t0 = time.perf_counter()
    stats = simulate(procedural_object("box", 0), cfg, folder / "seq")
    print(f"simulated {size[0]}x{size[1]}, {duration} s: {stats.num_events} events, "
          f"median pixel speed {stats.pixel_speed.get('p50', 0):.0f} px/s "
          f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    return Sequence.load(folder / "seq")


def _pose_source(seq: Sequence, weights: str | None, threads: int):
    if weights is None:
        return OraclePoseSource.from_sequence(seq, std_translation=0.01, std_rotation=0.03), \
            "oracle"
    from evtrack.models import OnnxPoseEstimator, TorchPoseEstimator

    cam = seq.meta.rgb_camera or seq.meta.event_camera
    est = (OnnxPoseEstimator(weights, cam, threads=threads, spin=False)
           if Path(weights).suffix.lower() == ".onnx"
           else TorchPoseEstimator.from_weights(weights, cam))
    return NetworkPoseSource(est, seq.meta.T_event_rgb), f"network {Path(weights).name}"


def _run(seq: Sequence, method: str, threads: int, config: dict, weights: str | None,
         cap: int | None, pose_async: bool = True, sample: int | None = None,
         search_budget: int | None = None, realtime_load: float | None = None,
         pose_prior: bool | None = None) -> dict:
    torch.set_num_threads(threads)
    changes = {**config, "method": method, "torch_threads": threads, "pose_async": pose_async}
    if pose_prior is not None:
        changes["pose_prior"] = pose_prior
    if cap is not None:
        changes["max_events_per_step"] = cap
    if sample is not None:
        changes["search_per_roi_window"] = sample
    if search_budget is not None:
        changes["max_searched_per_step"] = search_budget
    if realtime_load is not None:
        changes["realtime_load"] = realtime_load
    cfg = TrackerConfig.from_dict(changes)
    source, source_name = _pose_source(seq, weights, threads)
    tracker = Tracker.for_sequence(seq, cfg, source)
    groups: list[float] = []
    inner = tracker._group

    def timed_group(*args):
        t = time.perf_counter()
        inner(*args)
        groups.append(time.perf_counter() - t)

    tracker._group = timed_group
    t0 = time.perf_counter()
    traj = tracker.track(seq)
    wall = time.perf_counter() - t0
    span = (int(traj.t_us[-1]) - int(traj.t_us[0])) * 1e-6 if len(traj) > 1 else float("nan")
    st = tracker.stats
    filt = st.time_s.get("velocity", 0.0) + st.time_s.get("pose", 0.0)
    row = {"method": method, "threads": threads, "cap": cfg.max_events_per_step,
           "sample": cfg.search_per_roi_window, "budget": cfg.max_searched_per_step,
           "unsearched": st.events_unsearched, "rt": cfg.realtime_load,
           "budget_min": st.search_budget_min, "events_min": st.event_budget_min,
           "async": "on" if pose_async else "off",
           "prior": "on" if cfg.pose_prior else "off",
           "pose_src": st.time_s.get("pose_source", 0.0),
           "thinned": st.events_thinned, "source": source_name, "events": st.events,
           "seq_s": span, "proc_s": wall, "rtf": wall / span, "ev_per_s": st.events / wall,
           "flow": st.time_s.get("flow", 0.0), "velocity": st.time_s.get("velocity", 0.0),
           "pose": st.time_s.get("pose", 0.0),
           "frames": st.time_s.get("frames", 0.0),
           "group_p50_ms": 1e3 * statistics.median(groups) if groups else float("nan"),
           "group_p95_ms": 1e3 * float(np.quantile(groups, 0.95)) if groups else float("nan"),
           "step_us": 1e6 * filt / max(st.steps, 1)}
    if seq.ground_truth is not None:
        from evtrack.eval.metrics import tracking_errors

        err = tracking_errors(traj, seq.ground_truth)
        row["error"] = f"{err.position_rmse_cm:.2f} cm {err.rotation_rmse_deg:.2f} deg"
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, help="a sequence folder (default: simulate one)")
    ap.add_argument("--size", default="320x240", help="simulated image size WxH")
    ap.add_argument("--duration", type=float, default=1.0, help="simulated seconds")
    ap.add_argument("--threads", type=int, nargs="+", default=[2, 1])
    ap.add_argument("--methods", nargs="+", default=["full", "pose"])
    ap.add_argument("--roi-size", type=int, default=None,
                    help="flow RoI size (default: with --sequence the tracker's, 12 px, as "
                         "`evtrack evaluate` runs it; on the simulated sequence the demo's, "
                         "32 px at 640 px, scaled)")
    ap.add_argument("--batch-steps", type=int, default=TrackerConfig().flow_batch_steps,
                    metavar="N", help="flow_batch_steps: velocity steps per flow call")
    ap.add_argument("--mask-margin", type=float, default=None, metavar="PX",
                    help="mask_margin_px (default: the tracker's; on the simulated sequence "
                         "scaled to its width)")
    ap.add_argument("--weights", help="pose-network weights, .pt (torch) or .onnx "
                                      "(onnxruntime; default: the oracle)")
    ap.add_argument("--caps", type=int, nargs="+", default=[None], metavar="N",
                    help="max_events_per_step values to compare (0: no cap; default: the "
                         "config's)")
    ap.add_argument("--search-per-window", type=int, nargs="+", default=[None], metavar="N",
                    help="search_per_roi_window values to compare (events searched per RoI "
                         "window, a hash sample; 0: all; default: the config's)")
    ap.add_argument("--search-budget", type=int, nargs="+", default=[None], metavar="N",
                    help="max_searched_per_step values to compare (events searched per "
                         "velocity step, by cells of RoIs; 0: no budget; default: the config's)")
    ap.add_argument("--realtime-load", type=float, nargs="+", default=[None], metavar="L",
                    help="TrackerConfig.realtime_load values to compare (the search and event "
                         "budgets follow the processing load, live use; 0: off, the default)")
    ap.add_argument("--pose-async", nargs="+", choices=["on", "off"], default=["on"],
                    help="TrackerConfig.pose_async values to compare (on: the pose source in "
                         "the tracker's worker thread; default: on)")
    ap.add_argument("--pose-prior", nargs="+", choices=["on", "off"], default=[None],
                    help="TrackerConfig.pose_prior values to compare (on: the network looks "
                         "around the track's pose first; default: the config's)")
    ap.add_argument("--save-sequence", type=Path, metavar="DIR",
                    help="keep the simulated sequence in DIR (reuse it with --sequence DIR/seq)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        if args.sequence is not None:
            seq = Sequence.load(args.sequence)
        else:
            w, h = (int(v) for v in args.size.lower().split("x"))
            seq = _simulate((w, h), args.duration, args.save_sequence or Path(tmp))
        width = seq.meta.event_camera.width
        # a given sequence: the tracker's defaults, as `evtrack evaluate` tracks it; the
        # simulated one: the demo's pixel settings, scaled to the width (RoI 32 px and the
        # tracker's default mask margin at 640 px); either unless given
        pixels = TrackerConfig() if args.sequence is not None else demo_tracker_config(width)
        roi = args.roi_size or pixels.flow.roi_size
        margin = args.mask_margin if args.mask_margin is not None else pixels.mask_margin_px
        config = {"flow": {"roi_size": roi}, "mask_margin_px": margin,
                  "flow_batch_steps": args.batch_steps}
        rows = [_run(seq, m, th, config, args.weights, cap, mode == "on", sample, budget, rt,
                     None if prior is None else prior == "on")
                for th in args.threads for cap in args.caps for sample in args.search_per_window
                for budget in args.search_budget for rt in args.realtime_load
                for mode in args.pose_async for prior in args.pose_prior for m in args.methods]
    cam = seq.meta.event_camera
    print(f"\nevtrack.Tracker speed: {cam.width}x{cam.height}, RoI {roi} px, mask margin "
          f"{margin:g} px, "
          f"{rows[0]['events']} events over {rows[0]['seq_s']:.2f} s, pose source "
          f"{rows[0]['source']} at 5 Hz, 1 ms velocity steps, flow every {args.batch_steps} steps, "
          f"OMP_WAIT_POLICY {wait_policy()}")
    head = (f"{'method':<10} {'thr':>3} {'async':>5} {'prior':>5} {'cap':>6} {'sample':>6} "
            f"{'budget':>6} "
            f"{'rt':>4} {'min bgt':>7} {'min ev':>6} "
            f"{'unsearched':>10} {'thinned':>8} "
            f"{'proc s':>7} "
            f"{'rtf':>6} {'pose src':>8} "
            f"{'ev/s':>9} {'flow':>6} "
            f"{'veloc':>6} {'pose':>6} {'frames':>6} {'grp p50':>8} {'grp p95':>8} "
            f"{'filt/step':>9}  error")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['method']:<10} {r['threads']:>3} {r['async']:>5} {r['prior']:>5} {r['cap']:>6} "
              f"{r['sample']:>6} {r['budget']:>6} {r['rt']:>4g} {r['budget_min']:>7} "
              f"{r['events_min']:>6} "
              f"{r['unsearched']:>10} "
              f"{r['thinned']:>8} {r['proc_s']:>7.2f} {r['rtf']:>6.2f} "
              f"{r['pose_src']:>8.2f} "
              f"{r['ev_per_s']:>9.0f} {r['flow']:>6.2f} {r['velocity']:>6.2f} {r['pose']:>6.2f} "
              f"{r['frames']:>6.2f} {r['group_p50_ms']:>6.2f}ms {r['group_p95_ms']:>6.2f}ms "
              f"{r['step_us']:>7.0f}us  {r.get('error', '')}")
    print("rtf = processing time / sequence time; grp = one step group (one flow call): the "
          "output latency in live use; filt/step = velocity KF + pose UKF per 1 ms step.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
