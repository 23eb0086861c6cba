"""``evtrack track``: track the object of a sequence folder and write its trajectory."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from evtrack.errors import ConfigError
from evtrack.utils import check_writable

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "track",
        help="track the object of a sequence folder; write poses and twists (CSV or HDF5)",
        description=(
            "Run evtrack.Tracker over a sequence folder (events, RGB-D frames, object mesh) and "
            "write the trajectory: one pose and twist per velocity step (1 kHz by default). "
            "With ground truth in the folder, the position and rotation RMSE are printed. "
            "A sequence with several objects (evtrack simulate --object A --object B) is "
            "tracked by evtrack.MultiTracker: one trajectory per object, written beside --out "
            "as <stem>_<object><suffix>, with --oracle, each object's shipped network, or "
            "--mesh-only --start-from-ground-truth."
        ),
    )
    p.add_argument("sequence", type=Path, help="sequence folder (evtrack.Sequence)")
    p.add_argument("--out", type=Path, required=True,
                   help="trajectory file to write: .csv, .h5 or .hdf5")
    p.add_argument("--config", type=Path, default=None,
                   help="tracker config YAML (default: configs/tracker.yaml's defaults)")
    p.add_argument("--method", default=None,
                   choices=("full", "velocity", "pose", "frame-flow", "ge"),
                   help="tracking method (overrides the config's)")
    p.add_argument("--weights", type=Path, default=None,
                   help="pose-network weights (.pt or .onnx) for the pose source")
    p.add_argument("--oracle", action="store_true",
                   help="use the sequence's ground truth with noise as the pose source "
                        "(a test tool, not an estimator; needs groundtruth.h5)")
    p.add_argument("--oracle-noise", type=float, nargs=2, default=(0.01, 0.03),
                   metavar=("METRES", "RADIANS"),
                   help="oracle noise per axis (default: 0.01 m, 0.03 rad)")
    p.add_argument("--depth-refine", action="store_true",
                   help="refine each network pose on the sequence's depth frames (ICP with the "
                        "object's mesh)")
    p.add_argument("--depth-range", action="store_true",
                   help="also fuse the object's range measured on every depth frame (the mesh "
                        "at the predicted pose against the sensor depth; depth_fusion.range in the "
                        "config; not in the paper)")
    p.add_argument("--depth-icp", action="store_true",
                   help="also align the object's mesh with the depth frames (ICP from the "
                        "filter's pose) and fuse the aligned poses; depth_fusion.icp in the "
                        "config; "
                        "not in the paper")
    p.add_argument("--device", default=None, help="torch device (overrides the config's)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads while tracking (default: the config's torch_threads)")
    p.add_argument("--bop-results", type=Path, default=None, metavar="FILE.csv",
                   help="also write the tracked poses at the sequence's images as a BOP "
                        "challenge results CSV (scene_id,im_id,obj_id,score,R,t,time; t in mm), "
                        "in the camera frame of the BOP ground truth; for a sequence imported "
                        "from a BOP-layout dataset (evtrack import bop / ycbev)")
    p.add_argument("--start-pose", action="store_true",
                   help="start the track from the pose the import recorded in meta.yaml "
                        "(extra.start_pose at extra.start_t_us; 'evtrack import ecd' writes "
                        "it), so that '--method velocity' needs no pose source")
    p.add_argument("--start-from-ground-truth", action="store_true",
                   help="start the track from the ground truth's first pose (groundtruth.h5), "
                        "as a benchmark gives a tracker its start")
    p.add_argument("--start-box", type=float, nargs=4, default=None,
                   metavar=("U0", "V0", "U1", "V1"),
                   help="find the start pose on the first RGB-D frame from the object's textured "
                        "mesh alone, given this box around it in the RGB image (pixels; global "
                        "registration: the mesh fitted to the depth from many orientations, the "
                        "texture picking among them)")
    p.add_argument("--start-find", action="store_true",
                   help="as --start-box, without a box: the object is looked for where the first "
                        "depth frame stands out of the scene's dominant planes (table, walls) "
                        "with the object's size, and the region whose registration the colour "
                        "image confirms best is kept")
    p.add_argument("--mesh-only", action="store_true",
                   help="no pose network: correct the pose with the object's mesh alone "
                        "(pose_source: model: the mesh aligned with the depth frames, its "
                        "textured render with the RGB frames); needs a start pose "
                        "(--start-pose, --start-from-ground-truth, --start-box or --start-find). "
                        "Not in the paper")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _pose_source(args: argparse.Namespace, seq):
    from evtrack.tracking.pose_sources import NetworkPoseSource, OraclePoseSource

    if getattr(args, "mesh_only", False):
        given = [o for o, v in (("--weights", args.weights is not None), ("--oracle", args.oracle),
                                ("--depth-refine", args.depth_refine)) if v]
        if given:
            raise ConfigError(f"--mesh-only takes its poses from the mesh; {given[0]} gives "
                              "another pose source")
        return None
    if args.oracle and args.weights is not None:
        raise ConfigError("give either --weights or --oracle, not both")
    if args.oracle and args.depth_refine:
        raise ConfigError("--depth-refine refines a pose network's poses; not with --oracle")
    if args.oracle:
        if not all(math.isfinite(v) and v >= 0 for v in args.oracle_noise):
            raise ConfigError(f"--oracle-noise METRES RADIANS must be finite and >= 0, got "
                              f"{tuple(args.oracle_noise)}")
        return OraclePoseSource.from_sequence(seq, std_translation=args.oracle_noise[0],
                                              std_rotation=args.oracle_noise[1])
    if args.weights is None:
        if args.start_pose:
            return None
        raise ConfigError("a pose source is needed: --weights PATH (pose network) or --oracle "
                          "(or --start-pose with --method velocity)")
    cam = seq.meta.rgb_camera or seq.meta.event_camera
    if args.weights.suffix.lower() == ".onnx":
        from evtrack.models import OnnxPoseEstimator

        est = OnnxPoseEstimator(args.weights, cam, spin=False)  # it shares the cores
    else:
        from evtrack.models import TorchPoseEstimator

        est = TorchPoseEstimator.from_weights(args.weights, cam)
    refiner = None
    if args.depth_refine:
        from evtrack.models import DepthRefiner

        refiner = DepthRefiner.from_mesh(seq.mesh_file)
    return NetworkPoseSource(est, seq.meta.T_event_rgb, refiner=refiner, camera=cam)


def _start(args: argparse.Namespace, seq) -> dict:
    """The start pose and time of ``--start-pose`` or ``--start-from-ground-truth``, as
    keyword arguments of ``track``; ``{"box": box}`` for ``--start-box`` (registered once the
    tracker is built, :func:`_registered_start`). Checked before the tracker is built."""
    from_truth = getattr(args, "start_from_ground_truth", False)
    box = getattr(args, "start_box", None)
    find = getattr(args, "start_find", False)
    given = [o for o, v in (("--start-pose", args.start_pose),
                            ("--start-from-ground-truth", from_truth),
                            ("--start-box", box is not None), ("--start-find", find)) if v]
    if len(given) > 1:
        raise ConfigError(f"give one start: {' and '.join(given)} were given")
    if box is not None or find:
        return {"box": None if find else tuple(box)}
    if from_truth:
        gt = seq.ground_truth
        if gt is None:
            raise ConfigError(f"--start-from-ground-truth: {seq.root} has no groundtruth.h5")
        t0 = int(gt.pose_t_us[0])
        return {"start_pose": gt.pose_at(t0), "start_t_us": t0}
    if getattr(args, "mesh_only", False) and not args.start_pose:
        raise ConfigError("--mesh-only needs a start pose: --start-pose (recorded by the import), "
                          "--start-from-ground-truth, --start-box U0 V0 U1 V1 or --start-find")
    if not args.start_pose:
        return {}
    import numpy as np

    extra = seq.meta.extra if isinstance(seq.meta.extra, dict) else {}
    missing = [k for k in ("start_pose", "start_t_us") if k not in extra]
    if missing:
        raise ConfigError(f"--start-pose: {seq.root / 'meta.yaml'} has no extra.{missing[0]} "
                          "(written by 'evtrack import ecd'); give a pose source instead")
    try:
        pose = np.asarray(extra["start_pose"], np.float64).reshape(4, 4)
        t_us = int(extra["start_t_us"])
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"--start-pose: {seq.root / 'meta.yaml'}: extra.start_pose must be "
                          f"a 4x4 matrix and extra.start_t_us an integer ({exc})") from exc
    return {"start_pose": pose, "start_t_us": t_us}


def _first_rgbd_frame(seq, option: str) -> tuple:
    """``(t_us, rgb, depth)``: the first RGB frame and the depth frame nearest it, on which
    ``option`` registers the mesh."""
    import numpy as np

    if seq.num_rgb == 0 or seq.num_depth == 0:
        raise ConfigError(f"{option}: {seq.root} needs RGB and depth frames to register the "
                          "mesh on")
    t_us = int(seq.rgb_times_us[0])
    k = int(np.argmin(np.abs(seq.depth_times_us.numpy() - t_us)))
    return t_us, seq.rgb(0), seq.depth(k)


def _registered_start(seq, tracker, box) -> dict:
    """``--start-box`` / ``--start-find`` (``box`` None): the start pose registered on the
    first RGB frame and the depth frame nearest it."""
    option = "--start-find" if box is None else "--start-box"
    t_us, rgb, depth = _first_rgbd_frame(seq, option)
    try:
        found = tracker.start_from_frame(t_us, rgb, depth, None if box is None else tuple(box))
    except ValueError as exc:
        raise ConfigError(f"{option}: {exc}") from None
    runner = ("" if found.runner_up is None else
              f"; the next best, {found.runner_up[1]:.0f}° away, correlates "
              f"{found.runner_up[0]:.3f}")
    where = f" in the box {found.box} it found" if box is None else ""
    print(f"start pose registered on the frame at {t_us} µs{where}: the colour image correlates "
          f"{found.correlation:.3f} with the mesh there ({found.fitted} of {found.tried} "
          f"orientations fitted the depth){runner}")
    return {"start_pose": tracker.pose(), "start_t_us": t_us}


def run(args: argparse.Namespace) -> int:
    from evtrack import Sequence
    from evtrack.eval.metrics import tracking_errors
    from evtrack.tracking.config import TrackerConfig
    from evtrack.tracking.tracker import Tracker

    if args.out.suffix.lower() not in (".csv", ".h5", ".hdf5"):
        raise ConfigError(f"--out {args.out}: use a .csv, .h5 or .hdf5 file")
    check_writable(args.out, "--out")  # before the tracking, not after it
    seq = Sequence.load(args.sequence)
    if args.bop_results is not None:
        _check_bop_results(args.bop_results, seq)
    cfg = TrackerConfig.from_yaml(args.config) if args.config else TrackerConfig()
    changes: dict = {k: v for k, v in (("method", args.method), ("device", args.device),
                                       ("torch_threads", args.threads)) if v}
    fusion = {k: True for k, v in (("range", args.depth_range), ("icp", args.depth_icp)) if v}
    if fusion:
        changes["depth_fusion"] = fusion
    if getattr(args, "mesh_only", False):
        changes["pose_source"] = "model"
    cfg = TrackerConfig.from_dict(changes, "command line", base=cfg)
    if len(seq.objects) > 1:
        return _track_objects(args, seq, cfg)
    start = _start(args, seq)
    tracker = Tracker.for_sequence(seq, cfg, _pose_source(args, seq))
    if "box" in start:
        start = _registered_start(seq, tracker, start["box"])
    traj = tracker.track(seq, progress=not args.quiet, **start)
    traj.save(args.out)
    if args.bop_results is not None:
        _write_bop_results(args.bop_results, traj, seq)
    st = tracker.stats
    print(f"{args.out}: {len(traj)} samples ({cfg.method}), {int(traj.tracked.sum())} tracking; "
          f"{st.events} events"
          + (f" ({st.events_denoised} removed as noise, {st.events_on_hot_pixels} on "
             f"{st.hot_pixels} hot pixels)" if tracker.gate.denoiser is not None else "")
          + f", {st.poses} poses ({st.poses_rejected} rejected), "
          f"{st.lost} losses" + (f", {st.depth_ranges} depth ranges fused" if cfg.depth_fusion.range
                                 else "")
          + (f", {st.depth_alignments} depth alignments fused" if cfg.uses_depth_icp else "")
          + (f", {st.appearance_alignments} appearance alignments fused"
             if cfg.uses_appearance else ""))
    _print_unobserved(tracker)
    if st.roi_flows and st.depth_fallbacks > 0.5 * st.roi_flows:
        print(f"warning: {st.depth_fallbacks} of {st.roi_flows} RoI flows had no depth from the "
              "depth frames and took the fallback (the predicted depth of the object's centre); "
              "check the depth frames (missing, all zero, or in the wrong unit)", file=sys.stderr)
    if seq.ground_truth is not None:
        if not bool(traj.tracked.any()):
            print("error against ground truth: none, no sample was tracked (the pose source "
                  f"gave {st.poses} poses; are the weights for this object?)")
        else:
            print(f"error against ground truth: {tracking_errors(traj, seq.ground_truth)}")
    return 0


def object_out_path(out: Path, name: str) -> Path:
    """Where ``evtrack track`` writes object ``name``'s trajectory of a multi-object
    sequence: ``<stem>_<name><suffix>`` beside ``--out``."""
    return out.with_name(f"{out.stem}_{name}{out.suffix}")


def _track_objects(args: argparse.Namespace, seq, cfg) -> int:
    """``track`` on a sequence with several objects: one MultiTracker, a trajectory each."""
    from evtrack.eval.metrics import tracking_errors
    from evtrack.eval.pose_setup import PoseSourceSpec, make_pose_source, resolve_weights
    from evtrack.tracking.multi import MultiTracker, TrackedObject

    names = [o.name for o in seq.objects]
    for option, given in (("--weights", args.weights is not None),
                          ("--depth-refine", args.depth_refine),
                          ("--bop-results", args.bop_results is not None),
                          ("--start-pose", args.start_pose),
                          ("--start-box", getattr(args, "start_box", None) is not None)):
        if given:
            raise ConfigError(f"{seq.root} holds {len(names)} objects ({', '.join(names)}): "
                              f"{option} is for one object. Track them with --oracle, with "
                              "each object's shipped network (no pose option), or with "
                              "--mesh-only and --start-from-ground-truth or --start-find")
    views = [seq.object_view(k) for k in range(len(names))]
    start_t = None
    starts: dict = {}
    from_truth = getattr(args, "start_from_ground_truth", False)
    find = getattr(args, "start_find", False)
    if from_truth and find:
        raise ConfigError("give one start: --start-from-ground-truth and --start-find were given")
    if getattr(args, "mesh_only", False) and not (from_truth or find):
        raise ConfigError("--mesh-only with several objects needs --start-from-ground-truth or "
                          "--start-find")
    if from_truth:
        if any(v.ground_truth is None for v in views):
            raise ConfigError(f"--start-from-ground-truth: an object of {seq.root} has no "
                              "ground truth")
        start_t = int(views[0].ground_truth.pose_t_us[0])
        starts = {n: v.ground_truth.pose_at(start_t).numpy()
                  for n, v in zip(names, views, strict=True)}
    if getattr(args, "mesh_only", False):
        sources = [None] * len(views)
    elif args.oracle:
        if not all(math.isfinite(v) and v >= 0 for v in args.oracle_noise):
            raise ConfigError(f"--oracle-noise METRES RADIANS must be finite and >= 0, got "
                              f"{tuple(args.oracle_noise)}")
        spec = PoseSourceSpec("oracle", oracle_std_translation=args.oracle_noise[0],
                              oracle_std_rotation=args.oracle_noise[1])
        sources = [make_pose_source(spec, v) for v in views]
    else:
        spec = PoseSourceSpec("network")
        weights = resolve_weights(spec, names)
        sources = [make_pose_source(spec, v, weights[n]) for n, v in zip(names, views,
                                                                          strict=True)]
    multi = MultiTracker([TrackedObject(n, v.mesh_file, s) for n, v, s in zip(
        names, views, sources, strict=True)], cfg, camera=seq.meta.event_camera,
        rgb_camera=seq.meta.rgb_camera, T_event_rgb=seq.meta.T_event_rgb)
    if find:
        start_t, starts = _found_starts(seq, multi)
    tracks = multi.track(seq, progress=not args.quiet, start_poses=starts or None,
                         start_t_us=start_t)
    st = multi.stats
    print(f"{len(names)} objects, {st.events} events: "
          + ", ".join(f"{n} {c}" for n, c in st.per_object.items())
          + f", {st.unassigned} on none, {st.contested} in several silhouettes")
    for name, view in zip(names, views, strict=True):
        path = object_out_path(args.out, name)
        traj = tracks[name]
        traj.save(path)
        line = f"{path}: {len(traj)} samples ({cfg.method}), {int(traj.tracked.sum())} tracking"
        if view.ground_truth is not None and bool(traj.tracked.any()):
            line += f"; error against ground truth: {tracking_errors(traj, view.ground_truth)}"
        print(line)
        _print_unobserved(multi.trackers[name], f"{name}: ")
    return 0


def _found_starts(seq, multi) -> tuple[int, dict]:
    """``--start-find`` with several objects: each object's start pose found on the first
    RGB-D frame (:meth:`MultiTracker.start_from_frame
    <evtrack.tracking.multi.MultiTracker.start_from_frame>`), in the event camera."""
    t_us, rgb, depth = _first_rgbd_frame(seq, "--start-find")
    try:
        found = multi.start_from_frame(t_us, rgb, depth)
    except ValueError as exc:
        raise ConfigError(f"--start-find: {exc}") from None
    for name, reg in found.items():
        print(f"{name}: start pose registered on the frame at {t_us} µs in the box "
              f"{reg.box} it found (correlation {reg.correlation:.3f})")
    return t_us, {name: multi.trackers[name].T_event_rgb.numpy() @ reg.pose
                  for name, reg in found.items()}


def _print_unobserved(tracker, prefix: str = "") -> None:
    """Name the object axes about which the frame alignments did not observe the rotation
    (:meth:`~evtrack.tracking.tracker.Tracker.unobserved_rotations`)."""
    unobserved = tracker.unobserved_rotations()
    if unobserved:
        print(f"{prefix}the frame alignments did not observe the rotation "
              + "; ".join(u.describe() for u in unobserved)
              + " (one alignment's standard deviation; rotations about it come from the "
              "events" + (" and the pose source" if tracker.pose_source is not None else "")
              + " only)")


def _check_bop_results(path: Path, seq) -> None:
    """Before tracking: ``--bop-results`` is a writable ``.csv`` and the sequence has the BOP
    record it needs."""
    from evtrack.datasets.bop_results import bop_record

    if path.suffix.lower() != ".csv":
        raise ConfigError(f"--bop-results {path}: BOP results are a .csv file")
    check_writable(path, "--bop-results")
    bop_record(seq.meta)


def _write_bop_results(path: Path, traj, seq) -> None:
    from evtrack.datasets.bop_results import bop_record, sequence_bop_rows, write_bop_results

    rows = sequence_bop_rows(traj, seq.meta)
    write_bop_results(path, rows)
    print(f"{path}: {len(rows)} BOP results for the {len(bop_record(seq.meta)['im_ids'])} "
          "annotated images")
