"""Real-time factor of evtrack.Tracker with each kind of pose source, side by side in one process.

    python benchmarks/bench_tracker_sources.py --sequence DIR --weights W.pt [--onnx W.onnx]
        [--sources oracle torch onnx onnx-spin onnx+prior] [--repeats 2] [--threads 2]

Tracks one sequence (``full``, 5 Hz poses, the tracker's defaults, as ``evtrack evaluate``
runs it) once to warm up, then with each pose source in turn, ``--repeats`` rounds, so that
every source sees the same machine load:

* ``oracle``: ground truth with 1 cm / 0.03 rad noise (no network: the tracking's own cost);
* ``torch``: the network in torch (batch norms folded, the default);
* ``onnx``: the exported network on onnxruntime, its threads not spinning between calls (as
  ``evaluate`` and ``track`` run it); ``onnx-spin``: onnxruntime's default spinning threads;
* ``torch+prior``, ``onnx+prior``: the same with ``TrackerConfig.pose_prior`` (the network looks
  for the object on a crop around the track's pose first).

Without ``--onnx`` the weights are exported to a temporary ONNX file. Columns: the
real-time factor of each round (processing time / sequence time), the seconds spent in the
pose source per round (in the tracker's worker thread, sharing the cores), and the errors
against ground truth of the first round.

Timings on a shared machine are noisy; compare sources within one run of this script.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

# first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.runtime.openmp_wait)
import evtrack  # noqa: F401  # isort: skip
import torch

from evtrack import Sequence
from evtrack.eval.metrics import tracking_errors
from evtrack.models import OnnxPoseEstimator, TorchPoseEstimator, export_onnx, load_model
from evtrack.models.weights import read_record
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import NetworkPoseSource, OraclePoseSource
from evtrack.tracking.tracker import Tracker

SOURCES = ("oracle", "torch", "onnx", "onnx-spin", "torch+prior", "onnx+prior")


def make_source(kind: str, seq: Sequence, weights: Path, onnx: Path, threads: int):
    """The pose source ``kind`` (see the module docstring) for ``seq``."""
    if kind == "oracle":
        return OraclePoseSource.from_sequence(seq, std_translation=0.01, std_rotation=0.03)
    cam = seq.meta.rgb_camera or seq.meta.event_camera
    record, _ = read_record(weights)
    scale = record.input_size[1] / cam.width if record is not None else None
    backend = kind.split("+")[0]
    if backend == "torch":
        est = TorchPoseEstimator.from_weights(weights, cam, input_scale=scale)
    else:
        est = OnnxPoseEstimator(onnx, cam, threads=threads, spin=backend == "onnx-spin",
                                input_scale=scale, providers=["CPUExecutionProvider"])
    return NetworkPoseSource(est, seq.meta.T_event_rgb)


def track_once(seq: Sequence, kind: str, weights: Path, onnx: Path, threads: int):
    """(real-time factor, pose-source seconds, errors) of one run."""
    source = make_source(kind, seq, weights, onnx, threads)
    config = TrackerConfig.from_dict({"method": "full", "torch_threads": threads,
                                      "pose_prior": kind.endswith("+prior")})
    tracker = Tracker.for_sequence(seq, config, source)
    t0 = time.perf_counter()
    traj = tracker.track(seq)
    wall = time.perf_counter() - t0
    span = (int(traj.t_us[-1]) - int(traj.t_us[0])) * 1e-6
    errors = tracking_errors(traj, seq.ground_truth) if seq.ground_truth is not None else None
    return wall / span, tracker.stats.time_s.get("pose_source", 0.0), errors


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, required=True, help="a sequence folder")
    ap.add_argument("--weights", type=Path, required=True, help="the object's .pt weights")
    ap.add_argument("--onnx", type=Path, help="its ONNX export (default: exported here)")
    ap.add_argument("--sources", nargs="+", choices=SOURCES,
                    default=["oracle", "torch", "onnx", "onnx+prior"])
    ap.add_argument("--repeats", type=int, default=2, help="rounds over the sources")
    ap.add_argument("--threads", type=int, default=2, help="torch and onnxruntime threads")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    seq = Sequence.load(args.sequence)
    with tempfile.TemporaryDirectory() as tmp:
        onnx = args.onnx
        if onnx is None and any(k.startswith("onnx") for k in args.sources):
            net, _ = load_model(args.weights)
            onnx = export_onnx(net, Path(tmp) / "pose.onnx")
        track_once(seq, "oracle", args.weights, onnx, args.threads)  # warm-up
        rows: dict[str, list] = {kind: [] for kind in args.sources}
        for _ in range(args.repeats):
            for kind in args.sources:
                rows[kind].append(track_once(seq, kind, args.weights, onnx, args.threads))
                print(f"  {kind}: rtf {rows[kind][-1][0]:.2f}", file=sys.stderr)
    print(f"\nevtrack.Tracker (full, 5 Hz poses, {args.threads} threads) on {args.sequence.name}:"
          f" {args.repeats} rounds after a warm-up run")
    print(f"{'source':<12} {'rtf per round':>16} {'pose source s':>16}  errors (first round)")
    for kind, runs in rows.items():
        rtf = " ".join(f"{r[0]:.2f}" for r in runs)
        pose_s = " ".join(f"{r[1]:.2f}" for r in runs)
        err = runs[0][2]
        text = (f"{err.position_rmse_cm:.2f} cm {err.rotation_rmse_deg:.2f} deg"
                if err is not None else "")
        print(f"{kind:<12} {rtf:>16} {pose_s:>16}  {text}")
    print("rtf = processing time / sequence time (< 1: faster than real time)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
