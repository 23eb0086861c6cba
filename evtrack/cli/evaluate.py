"""``evtrack evaluate``: every tracking method on a benchmark, tables like the paper's (with the
ADD / ADD-S AUC and the 5 cm / 5° share beside the RMSE), plots."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from evtrack.errors import ConfigError

__all__ = ["register", "run"]

DESCRIPTION = """\
Track every sequence of a benchmark with each method and compare the trajectories with the
ground truth: RMSE ± σ of the position (cm, Euclidean) and of the rotation (deg, geodesic) per
sequence, per speed and averaged, printed like the paper's Tables I-II (and Table III with
--ablation) and saved as results.md and results.csv. Beside them, the pose accuracy as 6-DoF
trackers report it: the ADD AUC and the ADD-S AUC (%, thresholds up to 10 % of the object's
diameter; ADD-S forgives the object's symmetries) and the share of samples within 5 cm and 5°
at once (%), over every ground-truth sample, those before the first pose or while lost
counting as failures (a table of their own per sequence, and columns of Tables II-III and of
results.csv; '—' where a sequence has no mesh). Also writes every trajectory
(trajectories/<sequence>/<run>.h5), the tracking curves and the error against pixel velocity
and the pixel-velocity CDF (plots/), a manifest (results.yaml) and, with --video, an overlay
video per sequence (videos/).

BENCHMARK is a sequence folder or a folder of sequence folders (any folder holding meta.yaml),
e.g. the output of 'evtrack simulate-benchmark'. Every sequence needs ground truth.

Pose source: a pose network per object, found in --weights-dir (searched recursively, e.g.
runs/pose) or in the shipped zoo (models/weights); or --oracle: the ground-truth pose with
Gaussian noise, which tests the tracker but says nothing about a pose network (the tables say
ORACLE); or --oracle-where-missing: the network for the objects that have weights, the oracle
for the others (the caption names them). The networks run in torch (*.pt weights), or with
--backend onnxruntime as deployed (*.onnx models from 'evtrack export pose', searched the
same way). Each method on a sequence is tracked independently with the same pose-source seed.
Or --mesh-only: nothing trained, the full method corrects its pose with the object's mesh alone
(pose_source: model: the mesh aligned with the depth frames and its textured render with the
RGB frames), started from the ground truth's first pose; two columns, full-model (RGB-D) and
full-model-rgb (RGB frames only, the RoIs' depth rendered from the mesh).
"""

EPILOG = """\
examples:
  evtrack simulate-benchmark --out bench
  evtrack evaluate --benchmark bench --out bench-results --oracle --ablation --jobs 2
  evtrack evaluate --benchmark bench --weights-dir runs/pose --methods full pose --video
  evtrack evaluate --benchmark bench --oracle-where-missing --jobs 2
  evtrack export pose --weights runs/pose/box.pt --out onnx/box.onnx
  evtrack evaluate --benchmark bench --weights-dir onnx --backend onnxruntime
  evtrack evaluate --benchmark bench --out bench-mesh --mesh-only
  evtrack evaluate --benchmark bench --pose-latency-ms 0 --out bench-at-frame-times
  evtrack simulate-benchmark --out multi --multi-object two four
  evtrack evaluate --benchmark multi --oracle-where-missing --jobs 2
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from evtrack.eval.benchmark import DEFAULT_METHODS
    from evtrack.tracking.config import METHODS

    p = subparsers.add_parser(
        "evaluate", help="every method on a benchmark: error and ADD(-S) AUC tables, plots, "
                         "videos",
        description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--benchmark", type=Path, required=True, metavar="DIR",
                   help="a sequence folder or a folder of sequence folders")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=None,
                   metavar="METHOD",
                   help=f"methods (table columns, in this order); default: "
                        f"{' '.join(DEFAULT_METHODS)}")
    p.add_argument("--ablation", action="store_true",
                   help="also run the full method without the normal-flow constraint, "
                        "without measurement weighting, without the pose filter's velocity "
                        "bias (the paper's pose filter), with the range of every depth "
                        "frame fused (depth_fusion.range) and with the mesh aligned with the depth "
                        "frames (depth_fusion.icp), both not in the paper (Table III)")
    p.add_argument("--mesh-only", action="store_true",
                   help="no pose network: the full method with poses from the object's mesh "
                        "alone (pose_source: model), from the ground truth's first pose, with "
                        "RGB-D frames (full-model) and RGB frames only (full-model-rgb); "
                        "instead of --methods, --ablation and the pose-source options")
    p.add_argument("--out", type=Path, default=None, metavar="RESULTS_DIR",
                   help="results folder (default: <DIR>-results beside the benchmark)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--weights-dir", type=Path, default=None, metavar="D",
                     help="folder searched for each object's pose-network weights (*.pt, or "
                          "*.onnx with --backend onnxruntime; default: the shipped zoo, which "
                          "holds .pt weights)")
    src.add_argument("--oracle", action="store_true",
                     help="ground-truth poses with noise instead of a pose network")
    p.add_argument("--oracle-where-missing", action="store_true",
                   help="objects without pose-network weights get the oracle instead of an "
                        "error (the others keep their network; the caption names them)")
    p.add_argument("--oracle-noise", type=float, nargs=2, default=None,
                   metavar=("METRES", "RADIANS"),
                   help="oracle noise per axis (default: 0.01 m, 0.03 rad; with --oracle or "
                        "--oracle-where-missing)")
    p.add_argument("--backend", choices=("torch", "onnxruntime"), default="torch",
                   help="run the pose networks in torch (*.pt weights, the default) or on "
                        "onnxruntime (*.onnx models from 'evtrack export pose', as deployed; "
                        "they decode the same poses)")
    p.add_argument("--seed", type=int, default=0, help="seed of the oracle's noise (default 0)")
    p.add_argument("--depth-refine", action="store_true",
                   help="refine each network pose on the RGB-D depth frame (ICP with the "
                        "object's mesh) before the tracker uses it; the paper's estimator "
                        "is RGB only")
    p.add_argument("--config", type=Path, default=None,
                   help="tracker config YAML every run starts from (default: "
                        "configs/tracker.yaml's defaults); the runs set 'method' themselves")
    p.add_argument("--pose-latency-ms", type=float, default=None, metavar="MS",
                   help="when each pose reaches the filter after its frame (default: the "
                        "config's pose_latency_ms, 200: a network that runs at 5 Hz on a "
                        "small GPU or a CPU). 0: at its frame's time, as in an offline "
                        "evaluation that fuses each pose at its frame (the method paper's "
                        "tables state no latency)")
    p.add_argument("--video", action="store_true",
                   help="write an overlay video per sequence (full method and ground truth)")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="torch (and onnxruntime) CPU threads per run (default: the config's "
                        "torch_threads, 2; with "
                        "--jobs N, at most each job's share of the cores)")
    p.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="runs tracked in parallel worker processes (default 1)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier evaluation in RESULTS_DIR (its results.md, "
                        "results.csv, results.yaml, trajectories/, plots/ and videos/; other "
                        "files there stay)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def pose_spec(args: argparse.Namespace):
    """The :class:`~evtrack.eval.pose_setup.PoseSourceSpec` of the options."""
    from evtrack.eval.pose_setup import PoseSourceSpec

    fallback = args.oracle_where_missing
    if args.oracle_noise is not None and not (args.oracle or fallback):
        raise ConfigError("--oracle-noise needs --oracle or --oracle-where-missing")
    noise = args.oracle_noise or (0.01, 0.03)
    if not all(math.isfinite(v) and v >= 0 for v in noise):
        raise ConfigError(f"--oracle-noise METRES RADIANS must be finite and >= 0, got "
                          f"{tuple(noise)}")
    backend = getattr(args, "backend", "torch")
    if args.oracle and backend != "torch":
        raise ConfigError("--backend chooses how a pose network runs; not with --oracle")
    if args.oracle:
        return PoseSourceSpec("oracle", oracle_std_translation=noise[0],
                              oracle_std_rotation=noise[1], seed=args.seed,
                              depth_refine=getattr(args, "depth_refine", False),
                              oracle_fallback=fallback)
    if args.weights_dir is not None and not args.weights_dir.is_dir():
        raise ConfigError(f"--weights-dir {args.weights_dir}: folder not found")
    return PoseSourceSpec("network", weights_dir=args.weights_dir, seed=args.seed,
                          depth_refine=getattr(args, "depth_refine", False),
                          oracle_std_translation=noise[0], oracle_std_rotation=noise[1],
                          oracle_fallback=fallback, backend=backend)


def _check_mesh_only(args: argparse.Namespace) -> None:
    """Refuse the options --mesh-only replaces.

    Raises:
        ConfigError: naming the first such option.
    """
    clashes = {"--methods": args.methods is not None, "--ablation": args.ablation,
               "--oracle": args.oracle, "--oracle-where-missing": args.oracle_where_missing,
               "--weights-dir": args.weights_dir is not None,
               "--depth-refine": getattr(args, "depth_refine", False),
               "--backend onnxruntime": getattr(args, "backend", "torch") != "torch"}
    for option, given in clashes.items():
        if given:
            raise ConfigError(f"--mesh-only runs full-model and full-model-rgb without a pose "
                              f"source; {option} does not apply (evaluate the networks in a "
                              "run of their own)")


def run(args: argparse.Namespace) -> int:
    from evtrack.eval.benchmark import DEFAULT_METHODS, MESH_ONLY_RUNS, run_specs
    from evtrack.eval.pose_setup import pose_caption, resolve_weights
    from evtrack.eval.report import OUTPUT_NAMES
    from evtrack.eval.sequences import find_sequences, require_ground_truth, require_one_split
    from evtrack.tracking.config import TrackerConfig
    from evtrack.utils import output_folder

    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {args.threads}")
    if args.jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {args.jobs}")
    spec = pose_spec(args)
    if args.mesh_only:
        _check_mesh_only(args)
        runs = list(MESH_ONLY_RUNS)
    else:
        runs = run_specs(args.methods or DEFAULT_METHODS, args.ablation)
    base = TrackerConfig.from_yaml(args.config) if args.config else TrackerConfig()
    if args.pose_latency_ms is not None:
        base = base.replace(pose_latency_ms=_latency(args.pose_latency_ms))
    sequences = find_sequences(args.benchmark)
    require_ground_truth(sequences)
    require_one_split(sequences)
    if any(s.objects for s in sequences):
        return _run_multi_object(args, spec, base, sequences)
    objects = [s.object_name for s in sequences]
    if args.mesh_only:
        weights: dict = {}
        caption = ("no pose network: poses from the object's mesh alone (pose_source: model), "
                   "from the ground truth's first pose")
    else:
        weights = resolve_weights(spec, objects)
        caption = pose_caption(spec, weights, objects)
    bench = args.benchmark.resolve()
    out = args.out or bench.parent / f"{bench.name}-results"
    # a failed, interrupted or terminated evaluation leaves no half-written results
    with output_folder(out, OUTPUT_NAMES, args.overwrite, inputs={
            "--benchmark": args.benchmark, "--weights-dir": args.weights_dir,
            "--config": args.config}):
        return _evaluate(args, spec, runs, base, sequences, objects, weights, caption, out)


def _latency(value: float) -> float:
    """``--pose-latency-ms``, checked: finite and >= 0."""
    if not (math.isfinite(value) and value >= 0):
        raise ConfigError(f"--pose-latency-ms must be finite and >= 0, got {value}")
    return float(value)


def _run_multi_object(args: argparse.Namespace, spec, base, sequences) -> int:
    """``evaluate`` on sequences with several objects (see the description)."""
    from evtrack.eval.benchmark import MESH_ONLY_RUNS, run_specs
    from evtrack.eval.multi_object import (
        MULTI_OUTPUT_NAMES,
        evaluate_multi_object,
        write_multi_object_report,
    )
    from evtrack.eval.pose_setup import pose_caption, resolve_weights
    from evtrack.utils import output_folder

    single = [s.name for s in sequences if not s.objects]
    if single:
        raise ConfigError(f"the benchmark mixes one-object sequences {single[:3]} with "
                          "several-object ones; evaluate them in separate runs")
    for option, given in (("--ablation", args.ablation), ("--video", args.video)):
        if given:
            raise ConfigError(f"{option} is for one-object sequences; the multi-object "
                              "evaluation compares each object together and alone")
    if args.mesh_only:
        _check_mesh_only(args)
        runs = [MESH_ONLY_RUNS[0]]
        weights: dict = {}
        caption = ("no pose network: poses from each object's mesh alone (pose_source: "
                   "model), from the ground truth's first pose")
    else:
        runs = run_specs(args.methods or ("full",))
        objects = sorted({name for s in sequences for name in s.objects})
        weights = resolve_weights(spec, objects)
        caption = pose_caption(spec, weights, objects)
    bench = args.benchmark.resolve()
    out = args.out or bench.parent / f"{bench.name}-results"
    with output_folder(out, MULTI_OUTPUT_NAMES, args.overwrite, inputs={
            "--benchmark": args.benchmark, "--weights-dir": args.weights_dir,
            "--config": args.config}):
        print(f"evaluating {len(sequences)} multi-object sequence(s) x {len(runs)} run(s), "
              f"each object together and alone; pose source: {caption}")
        results, timings = evaluate_multi_object(
            sequences, runs, base, spec, weights, out, jobs=args.jobs,
            torch_threads=args.threads, progress=not args.quiet)
        markdown = write_multi_object_report(
            results, timings, out, caption,
            {"benchmark": str(args.benchmark), "tracker_config": base.to_dict()})
    print()
    print(markdown)
    print(f"wrote {out}/: multi_object.md, multi_object.csv, multi_object.yaml, trajectories/")
    return 0


def _evaluate(args, spec, runs, base, sequences, objects, weights, caption, out: Path) -> int:
    """Track, measure and write the report (see :func:`run`)."""
    from evtrack.eval.benchmark import pose_warnings, rotation_notes, run_benchmark
    from evtrack.eval.report import write_report

    print(f"evaluating {len(sequences)} sequence(s) x {len(runs)} run(s) "
          f"[{', '.join(r.name for r in runs)}]; pose source: {caption}")
    for name, path in weights.items():
        print(f"  weights for {name}: {path}")
    results = run_benchmark(sequences, runs, base, spec, weights, out, jobs=args.jobs,
                            torch_threads=args.threads, progress=not args.quiet)
    info = {"benchmark": str(args.benchmark), "tracker_config": base.to_dict(),
            "weights": {k: str(weights[k]) if k in weights else "oracle"
                        for k in sorted(set(objects))}
            if spec.kind == "network" and not getattr(args, "mesh_only", False) else {}}
    files = write_report(results, sequences, runs, out, caption=caption, info=info,
                         video=args.video, progress=not args.quiet)
    print()
    print(files.markdown)
    for line in pose_warnings(results) + rotation_notes(results):
        print(line)
    print(f"wrote {out}/: results.md, results.csv, results.yaml, trajectories/ "
          f"({len(results)} files), plots/ ({len(files.plots)} PNG)"
          + (f", videos/ ({len(files.videos)} MP4)" if files.videos else ""))
    return 0
