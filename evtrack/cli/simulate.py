"""``evtrack simulate`` and ``evtrack simulate-benchmark``: synthetic sequences.

``simulate`` renders one object moving along a random smooth 6-DoF trajectory and writes a
sequence folder (events, 60 FPS motion-blurred RGB, depth, ground truth). ``simulate-benchmark``
makes the paper's benchmark set: four YCB objects x {regular, faster}, fixed seeds, 640x480.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from evtrack.errors import ConfigError, EvtrackError

__all__ = ["register", "run_simulate", "run_benchmark", "build_config"]


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path, default=None,
                        help="simulation config YAML (e.g. configs/sim_regular.yaml); command-line "
                             "options override it")
    parser.add_argument("--duration", type=float, default=None,
                        help="sequence length in seconds (default: 2)")
    parser.add_argument("--width", type=int, default=None,
                        help="image width in pixels; the field of view is kept (default: 640)")
    parser.add_argument("--height", type=int, default=None,
                        help="image height in pixels (default: 480)")
    parser.add_argument("--render-hz", type=float, default=None,
                        help="render rate feeding the event model (default: 500)")
    parser.add_argument("--device", default=None,
                        help="torch device of the event simulator: cpu or cuda (default: cpu)")
    parser.add_argument("--ycb-dir", type=Path, default=None,
                        help="folder with the YCB object folders (default: $EVTRACK_YCB_DIR or "
                             "../shared/data/ycb)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace existing output folders (default: refuse)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate a sequence: events, blurred RGB-D and ground truth of a moving object",
        description=(
            "Render a textured object moving along a random smooth 6-DoF trajectory at 500 FPS "
            "(--render-hz), turn the renders into events (log-intensity event-camera model), "
            "average them into 60 FPS motion-blurred RGB with depth, and write a sequence "
            "folder with ground-truth poses, twists and per-event optical flow."
        ),
    )
    p.add_argument("--object", required=True, action="append", metavar="OBJECT",
                   help="a procedural object (no download): coded_box (the one the shipped "
                        "demo network knows), box, can or bottle; a YCB name such as "
                        "003_cracker_box; a mesh file (glTF/GLB/OBJ/PLY, metres); or a BOP "
                        "model, in millimetres and scaled to metres: a file obj_000005.ply "
                        "beside a models_info.json, or bop:MODELS_DIR:5. Repeat it for "
                        "several objects in one sequence (each on its own trajectory, the "
                        "first is the sequence's object; see --layout)")
    p.add_argument("--layout", choices=("crossing", "apart"), default=None,
                   help="with several objects: 'crossing' (default), each in its own depth "
                        "band, all moving about the middle of the image, so that they pass in "
                        "front of one another; 'apart', each in its own cell of the image, "
                        "none occluding another")
    p.add_argument("--speed", choices=("regular", "faster"), default=None,
                   help="trajectory preset (default: regular, or the config's)")
    p.add_argument("--seed", type=int, default=None,
                   help="random seed of the trajectory, scene and sensor noise (default: 0)")
    p.add_argument("--object-seed", type=int, default=0,
                   help="texture seed of the procedural objects; the shipped pose-network "
                        "weights know the textures of seed 0 (default: 0)")
    p.add_argument("--out", type=Path, required=True, help="sequence folder to create")
    p.add_argument("--adaptive", action="store_true",
                   help="add renders where the log intensity changes too fast between renders")
    p.add_argument("--randomize", action="store_true",
                   help="random background, lighting and distractors (for training data)")
    _add_common(p)
    p.set_defaults(func=run_simulate)

    b = subparsers.add_parser(
        "simulate-benchmark",
        help="simulate the benchmark set: 4 YCB objects x {regular, faster}",
        description=(
            "Make the benchmark set of the paper's synthetic experiments: 003_cracker_box, "
            "005_tomato_soup_can, 006_mustard_bottle and 010_potted_meat_can, each with a "
            "regular and a faster trajectory (fixed seeds), 640x480, 2 s. Writes OUT/<object>_"
            "<preset>/ folders, OUT/velocity_cdf.png and OUT/summary.yaml. With --split, the "
            "held-out protocol: the tuning or the test split, the same cells with --seeds seeds "
            "each and no seed in common between the splits, in OUT/<object>_<preset>_seed<N>/ "
            "folders; choose settings on the tuning split and report the test split "
            "(docs/results.md, 'Evaluation protocol')."
        ),
    )
    b.add_argument("--out", type=Path, required=True,
                   help="folder for the sequences (eight for the fixed set)")
    b.add_argument("--objects", nargs="+", default=None, metavar="NAME",
                   help="only these YCB objects (default: all four)")
    b.add_argument("--presets", nargs="+", choices=("regular", "faster"), default=None,
                   help="only these presets (default: both)")
    b.add_argument("--preset-speeds", nargs="+", default=None, metavar="PRESET=LIN,ANG",
                   help="mean speeds of a preset instead of its defaults: linear m/s and "
                        "angular rad/s, e.g. 'faster=0.5,0.9' (same seeds and waypoints, "
                        "traversed at these speeds; defaults: regular=0.3,1.0 "
                        "faster=0.8,2.5); recorded per sequence in summary.yaml. 'paper': "
                        "regular=0.24,0.76 faster=0.8,1.0, the speeds at which the pose-only "
                        "baseline errs about as much as the paper's (see "
                        "evtrack.sim.benchmark_set.PAPER_MATCHED_SPEEDS)")
    b.add_argument("--split", choices=("tuning", "test"), default=None,
                   help="simulate a split of the held-out protocol instead of the fixed set "
                        "(which is the tuning split's first seed): seeds 1000+100k+10i+j "
                        "(tuning) or 5000+100k+10i+j (test) for object i, preset j, replicate k")
    b.add_argument("--seeds", type=int, default=None, metavar="K",
                   help="seeds per object and preset of the split (default 3: each column "
                        "average then holds 12 sequences, and its spread over seeds is "
                        "reported by 'evtrack evaluate'); needs --split")
    b.add_argument("--replicates", type=int, nargs="+", default=None, metavar="k",
                   help="only these replicates (0-based seed indices) of the split, e.g. to "
                        "simulate a split in parts; needs --split")
    b.add_argument("--multi-object", nargs="+", choices=("two", "four"), default=None,
                   metavar="SET",
                   help="instead, the multi-object sets: 'two' (tomato soup can + cracker "
                        "box, potted meat can + mustard bottle) and/or 'four' (all four in one "
                        "stream), each in the 'apart' layout (no occlusion) and the "
                        "'crossing' layout (they pass in front of one another), for each "
                        "--presets (default: regular); in OUT/<set>/<objects>_<layout>_"
                        "<preset>/, evaluated per object by 'evtrack evaluate'")
    b.add_argument("--velocity-only", action="store_true",
                   help="only write the pixel-velocity report (velocity_cdf.png, summary.yaml) "
                        "from the trajectories, without rendering (seconds instead of minutes)")
    _add_common(b)
    b.set_defaults(func=run_benchmark)


def build_config(args: argparse.Namespace):
    """The :class:`~evtrack.sim.config.SimConfig` from ``--config`` and the options."""
    from evtrack.sim.config import SimConfig, load_config
    from evtrack.sim.engine import preset_config

    cfg = load_config(args.config) if args.config else SimConfig()
    changes = {}
    if args.duration is not None:
        changes["duration"] = args.duration
    if getattr(args, "seed", None) is not None:
        changes["seed"] = args.seed
    if args.width is not None or args.height is not None:
        for name in ("width", "height"):
            if getattr(args, name) is not None and getattr(args, name) <= 0:
                raise ConfigError(f"--{name} must be positive, got {getattr(args, name)}")
        w = args.width if args.width is not None else cfg.camera.width
        h = args.height if args.height is not None else round(
            cfg.camera.height * w / cfg.camera.width)
        if w <= 0 or h <= 0:
            raise ConfigError(f"--width/--height must be positive, got {w}x{h}")
        changes["camera"] = cfg.camera.resized(w, h)
    if args.render_hz is not None:
        changes["render"] = dataclasses.replace(cfg.render, render_hz=args.render_hz)
    if getattr(args, "adaptive", False):
        changes["render"] = dataclasses.replace(changes.get("render", cfg.render), adaptive=True)
    if args.device is not None:
        changes["events"] = dataclasses.replace(cfg.events, device=args.device)
    if getattr(args, "randomize", False):
        changes["scene"] = dataclasses.replace(cfg.scene, randomize=True)
    cfg = dataclasses.replace(cfg, **changes)
    if getattr(args, "speed", None) is not None:
        cfg = preset_config(cfg, args.speed)
    if getattr(args, "layout", None) is not None:
        cfg = dataclasses.replace(cfg, trajectory=dataclasses.replace(cfg.trajectory,
                                                                      layout=args.layout))
    return cfg


def _check_device(device: str) -> None:
    import torch

    if torch.device(device).type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"--device {device}: CUDA is not available on this machine")


def run_simulate(args: argparse.Namespace) -> int:
    from evtrack.sim.engine import simulate
    from evtrack.sim.objects import resolve_object

    cfg = build_config(args)
    _check_device(cfg.events.device)
    if args.out.exists() and not args.overwrite:
        raise EvtrackError(f"{args.out} exists; pass --overwrite to replace it")
    objects = [resolve_object(spec, seed=args.object_seed, ycb_dir=args.ycb_dir)
               for spec in args.object]
    names = [o.name for o in objects]
    if len(set(names)) != len(names):
        raise ConfigError(f"--object: each object must be another one, got {names}")
    if args.layout is not None and len(objects) == 1:
        raise ConfigError("--layout places several objects; give --object more than once")
    stats = simulate(objects if len(objects) > 1 else objects[0], cfg, args.out,
                     overwrite=args.overwrite, progress=not args.quiet)
    speed = stats.pixel_speed
    print(f"wrote {args.out}: {stats.num_events} events, {stats.num_rgb} RGB-D frames, "
          f"{stats.num_renders} renders in {stats.timings['total']:.1f} s")
    if len(objects) > 1:
        print(f"objects: {', '.join(names)} (layout {cfg.trajectory.layout}); the pixel "
              f"speed is {names[0]}'s")
    print(f"object pixel speed (px/s): median {speed['p50']:.0f}, p90 {speed['p90']:.0f}, "
          f"p99 {speed['p99']:.0f}")
    return 0


def parse_preset_speeds(items: list[str] | None) -> dict[str, tuple[float, float]]:
    """``["faster=0.5,0.9", ...]`` -> ``{"faster": (0.5, 0.9)}`` (m/s, rad/s); ``["paper"]``
    -> :data:`~evtrack.sim.benchmark_set.PAPER_MATCHED_SPEEDS`.

    Raises:
        ConfigError: naming the item: not ``PRESET=LIN,ANG``, an unknown preset, a preset
            given twice, or a speed that is not a positive finite number.
    """
    import math

    from evtrack.sim.benchmark_set import PAPER_MATCHED_SPEEDS, PRESETS

    if items and "paper" in items:
        if len(items) > 1:
            raise ConfigError("--preset-speeds paper sets both presets; give it alone")
        return dict(PAPER_MATCHED_SPEEDS)
    out: dict[str, tuple[float, float]] = {}
    for item in items or []:
        preset, sep, values = item.partition("=")
        parts = values.split(",")
        if not sep or len(parts) != 2:
            raise ConfigError(f"--preset-speeds {item!r}: expected PRESET=LINEAR,ANGULAR "
                              "(m/s, rad/s), e.g. faster=0.5,0.9")
        if preset not in PRESETS:
            raise ConfigError(f"--preset-speeds {item!r}: unknown preset {preset!r} "
                              f"(one of {', '.join(PRESETS)})")
        if preset in out:
            raise ConfigError(f"--preset-speeds: {preset!r} given twice")
        try:
            linear, angular = (float(v) for v in parts)
        except ValueError:
            raise ConfigError(f"--preset-speeds {item!r}: the speeds must be numbers") from None
        if not (math.isfinite(linear) and math.isfinite(angular) and linear > 0
                and angular > 0):
            raise ConfigError(f"--preset-speeds {item!r}: the speeds must be positive and "
                              "finite")
        out[preset] = (linear, angular)
    return out


def _selected_entries(args: argparse.Namespace) -> list:
    """The entries ``simulate-benchmark`` makes: the fixed set or a split's, then only the
    ``--objects``, ``--presets`` and ``--replicates`` asked for."""
    from evtrack.sim.benchmark_set import (
        DEFAULT_SPLIT_SEEDS,
        MAX_SEEDS,
        BenchmarkEntry,
        benchmark_entries,
        split_entries,
    )

    if args.split is None:
        for flag in ("seeds", "replicates"):
            if getattr(args, flag) is not None:
                raise ConfigError(f"--{flag} needs --split tuning or --split test")
        entries = [BenchmarkEntry(*e) for e in benchmark_entries()]
    else:
        seeds = DEFAULT_SPLIT_SEEDS if args.seeds is None else args.seeds
        if not 1 <= seeds <= MAX_SEEDS:
            raise ConfigError(f"--seeds must be in 1..{MAX_SEEDS}, got {seeds}")
        entries = split_entries(args.split, seeds)
        if args.replicates is not None:
            bad = sorted(k for k in set(args.replicates) if not 0 <= k < seeds)
            if bad:
                raise ConfigError(f"--replicates {bad}: a split of {seeds} seed(s) has "
                                  f"replicates 0..{seeds - 1}")
            entries = [e for e in entries if e.replicate in args.replicates]
    if args.objects:
        known = {e.object_name for e in entries} | {e.object_name[4:] for e in entries}
        unknown = sorted(set(args.objects) - known)
        if unknown:
            raise ConfigError(f"--objects: unknown YCB object(s) {unknown}")
        entries = [e for e in entries
                   if e.object_name in args.objects or e.object_name[4:] in args.objects]
    if args.presets:
        entries = [e for e in entries if e.preset in args.presets]
    return entries


def _run_multi_object_sets(args: argparse.Namespace, cfg) -> int:
    from evtrack.sim.multi_object_set import make_multi_object_set

    clashes = {"--objects": args.objects, "--preset-speeds": args.preset_speeds,
               "--split": args.split, "--seeds": args.seeds, "--replicates": args.replicates,
               "--velocity-only": args.velocity_only}
    for option, given in clashes.items():
        if given:
            raise ConfigError(f"--multi-object makes the fixed multi-object sets; {option} "
                              "does not apply")
    try:
        summary = make_multi_object_set(args.out, cfg, sets=args.multi_object,
                                        presets=args.presets or ("regular",),
                                        ycb_dir=args.ycb_dir, overwrite=args.overwrite,
                                        progress=not args.quiet)
    except FileExistsError as exc:
        raise EvtrackError(f"{exc} (use --overwrite)") from None
    for name, row in summary["sequences"].items():
        print(f"{name:56s} {row['events']:>10d} events {row['rgb_frames']:>4d} frames "
              f"{row['seconds']:6.1f} s")
    print(f"wrote {args.out}/summary.yaml")
    return 0


def run_benchmark(args: argparse.Namespace) -> int:
    from evtrack.sim.benchmark_set import make_benchmark_set, velocity_report

    cfg = build_config(args)
    speeds = parse_preset_speeds(args.preset_speeds)
    _check_device(cfg.events.device)
    if args.multi_object:
        return _run_multi_object_sets(args, cfg)
    entries = _selected_entries(args)
    if args.velocity_only:
        summary = velocity_report(args.out, cfg, ycb_dir=args.ycb_dir, entries=entries,
                                  speeds=speeds)
        for name, row in summary["sequences"].items():
            s = row["pixel_speed_px_s"]
            print(f"{name:32s} median {s['p50']:7.0f}  p90 {s['p90']:7.0f}  "
                  f"p99 {s['p99']:7.0f} px/s")
        print(f"wrote {args.out}/velocity_cdf.png and {args.out}/summary.yaml")
        return 0
    try:
        summary = make_benchmark_set(args.out, cfg, ycb_dir=args.ycb_dir, entries=entries,
                                     overwrite=args.overwrite, progress=not args.quiet,
                                     speeds=speeds)
    except FileExistsError as exc:
        raise EvtrackError(f"{exc} (use --overwrite)") from None
    for name, row in summary["sequences"].items():
        print(f"{name:32s} {row['events']:>10d} events {row['rgb_frames']:>4d} frames "
              f"median {row['pixel_speed_px_s']['p50']:7.0f} px/s  {row['seconds']:6.1f} s")
    print(f"wrote {args.out}/velocity_cdf.png and {args.out}/summary.yaml")
    return 0
