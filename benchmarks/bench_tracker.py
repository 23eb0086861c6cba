"""Real-time factor and update latency of evtrack.Tracker on CPU, optionally against the tracker
of an older git revision, side by side.

    python benchmarks/bench_tracker.py [--size 320x240] [--duration 1.0] [--threads 2 1]
                                       [--methods full pose] [--sequence DIR] [--weights W.pt]
                                       [--caps 0 2000 1000] [--search-per-window 0 128 64]
                                       [--pose-async off on] [--pose-prior off on]
                                       [--save-sequence DIR]
    python benchmarks/bench_tracker.py --benchmark SETDIR [--speed faster] [--oracle]
                                       [--baseline REV] [--repeats 3] [--duration S] ...
    python benchmarks/bench_tracker.py --sequences DIR [DIR ...] [--baseline REV] [--new REV]
                                       [--export-dir DIR] ...

Simulates a ``faster`` sequence of the procedural box (or takes ``--sequence``), then tracks it
with each method and thread count, side by side. The pose source is the oracle (ground truth
with 1 cm / 0.03 rad noise) unless ``--weights`` gives pose-network weights (then the network
runs at 5 Hz on the RGB frames, on CPU, loaded as ``evtrack track`` loads it; an ``.onnx`` file
on onnxruntime with the row's threads, not spinning between calls).

Several recorded sequences: ``--sequences DIR ...``, or ``--benchmark SETDIR`` (its ``faster``
sequences, ``--speed`` for others; e.g. from ``evtrack simulate-benchmark``), tracked with the
tracker's defaults and the pose source as ``evtrack evaluate`` builds them: the shipped pose
network of each sequence's object (``models/weights``, in torch, at its training resolution),
one ``--weights`` file for all, or ``--oracle``. ``--duration S`` tracks the first S seconds of
each sequence (default: all of it).

Old against new: ``--baseline REV`` exports the package of git revision REV (``git archive`` of
``evtrack/``, ``models/``, ``filters/``, ``train/``, assembled as the installed package maps
them) and runs every row with both trees, each in a child process of its own (``PYTHONPATH``
naming the export for the old one; the same interpreter, environment and thread settings),
the runs of old and new alternating (old, new, then new, old...) so that the machine's load
hits both alike; ``--repeats N`` takes the median of N runs each. The children use only what
both trees have (``evtrack.Sequence``, ``Tracker``, ``TrackerConfig``,
``evtrack.eval.pose_setup``, ``evtrack.eval.metrics``); each tracks every method once untimed
before its timed runs (the first run of a process loads or compiles the numba kernels;
``--no-warmup`` skips it; a fresh export compiles them, which ``--export-dir`` keeps for the
next invocation). Printed per row: the old and the new run, the ratio new/old of the
processing time, and whether the trajectories are the same (bit for bit). The new side is the
package as installed (the working tree), or ``--new REV``, exported the same way; this process
itself (the sequence list, the weights files, the simulation) always uses the installed one.

The first lines of the output are the reference of the measurement: the command, the date,
the CPU, and the commit of each tree (the new one with a note when it has uncommitted
changes).

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
    cap: ``load.max_events_per_step`` (events per 1 ms step entering the flow; thinned above it):
        ``--caps`` compares the speed and the error of several budgets.
    sample: ``load.search_per_roi_window`` (events of a RoI window searched for candidates, a hash
        sample; 0: all): ``--search-per-window`` compares several.
    rt, min bgt, min ev: ``load.realtime`` (0: off), the lowest search budget and the lowest
        event budget per step it set (0: none); ``--realtime-load 0 0.9`` compares the
        deterministic default with live use.
    runs: the processing time of each run (with ``--repeats``; the other columns are medians).
    new/old: the new tree's median processing time over the old tree's (``--baseline``).
    traj: ``same``: old and new gave bit-identical trajectories in every run; ``differs``: in
        none; ``varies``: the runs of one tree differ among themselves.

Timings on a shared machine are noisy; rerun when it is quiet.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import hashlib
import importlib
import json
import math
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

# first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.runtime.openmp_wait)
import evtrack  # noqa: F401  # isort: skip
import numpy as np
import torch

# beside this script (a script's folder is on the import path)
from revision_trees import export_package, resolve_revision, tree_commit
from tracker_tables import print_compact, print_wide

# only names both the current and older trees have: a --baseline child imports this module
# with the older package
from evtrack import Sequence, Tracker, TrackerConfig

#: The oracle's noise per axis (m, rad), as ``evtrack evaluate --oracle`` sets it.
ORACLE_NOISE = (0.01, 0.03)


# ----------------------------------------------------------------------------- measurement
def _first_module(*names: str):
    """The first of ``names`` that exists (a module moved between revisions); a module that
    exists but fails to import raises."""
    for name in names:
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name is None or not name.startswith(exc.name):
                raise
    raise ModuleNotFoundError(f"none of {names}")


def _simulate(size: tuple[int, int], duration: float, folder: Path) -> Path:
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
    return folder / "seq"


def truncate(seq: Sequence, seconds: float) -> None:
    """Keep the first ``seconds`` of ``seq`` (from its first event): its frames before then
    and a stream of events that stops there."""
    first = seq.iter_events(count=1)
    try:
        head = next(first, None)
    finally:
        first.close()
    if head is None or not len(head):
        return
    t_end = int(head.t[0]) + round(seconds * 1e6)
    seq.rgb_times_us = seq.rgb_times_us[seq.rgb_times_us < t_end]
    seq.depth_times_us = seq.depth_times_us[seq.depth_times_us < t_end]
    stream = seq.iter_events

    def iter_events(window_us=None, count=None):
        for chunk in stream(window_us=window_us, count=count):
            if len(chunk) and int(chunk.t[-1]) >= t_end:
                k = int(torch.searchsorted(chunk.t, torch.tensor([t_end]))[0])
                if k:
                    yield chunk[:k]
                return
            yield chunk

    seq.iter_events = iter_events


def _pose_source(seq: Sequence, pose: dict, threads: int):
    """The pose source of a run and its name. ``pose``: ``{"loader": "evaluate" | "track",
    "weights": path or None (the oracle)}``."""
    weights = pose.get("weights")
    if pose["loader"] == "evaluate":
        from evtrack.eval.pose_setup import PoseSourceSpec, make_pose_source

        if weights is None:
            spec = PoseSourceSpec("oracle", oracle_std_translation=ORACLE_NOISE[0],
                                  oracle_std_rotation=ORACLE_NOISE[1])
            return make_pose_source(spec, seq), "oracle"
        spec = PoseSourceSpec("network", weights=Path(weights))
        return (make_pose_source(spec, seq, Path(weights), threads=threads),
                f"network {Path(weights).name}")
    sources = _first_module("evtrack.tracking.pose_sources", "evtrack.pose_sources")
    if weights is None:
        return sources.OraclePoseSource.from_sequence(
            seq, std_translation=ORACLE_NOISE[0], std_rotation=ORACLE_NOISE[1]), "oracle"
    from evtrack.models import OnnxPoseEstimator, TorchPoseEstimator

    cam = seq.meta.rgb_camera or seq.meta.event_camera
    est = (OnnxPoseEstimator(weights, cam, threads=threads, spin=False)
           if Path(weights).suffix.lower() == ".onnx"
           else TorchPoseEstimator.from_weights(weights, cam))
    return sources.NetworkPoseSource(est, seq.meta.T_event_rgb), f"network {Path(weights).name}"


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _plain(value):
    """``value`` as JSON can carry it (numpy and torch scalars to Python numbers)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.generic, torch.Tensor)):
        return value.item()
    return value


def _option(cfg, section: str, name: str, flat: str | None = None):
    """A tracker option by its place in the config's sections, or by its flat name in the
    config of a tree from before the sections (``flat``: that name where it differs)."""
    part = getattr(cfg, section, None)
    if part is not None and hasattr(part, name):
        return getattr(part, name)
    return getattr(cfg, flat or name)


def measure(job: dict) -> dict:
    """Track one sequence once and time it; the row of the tables.

    ``job``: ``sequence`` (folder), ``duration`` (seconds to track, ``None``: all),
    ``threads``, ``config`` (``TrackerConfig.from_dict`` changes, the method among them) and
    ``pose`` (see :func:`_pose_source`). Uses only what every tree compared has.
    """
    threads = job["threads"]
    torch.set_num_threads(threads)
    seq = Sequence.load(job["sequence"])
    if job.get("duration") is not None:
        truncate(seq, job["duration"])
    with warnings.catch_warnings():  # the rows' flat option names: read by both trees
        warnings.simplefilter("ignore", FutureWarning)
        cfg = TrackerConfig.from_dict(job["config"])
    source, source_name = _pose_source(seq, job["pose"], threads)
    tracker = Tracker.for_sequence(seq, cfg, source)
    groups: list[float] = []
    # the step group's processing: the scheduler's (evtrack.tracking.scheduler) or, in a tree
    # from before the tracker's parts, the tracker's own method
    owner, name = ((tracker.scheduler, "run_group") if hasattr(tracker, "scheduler")
                   else (tracker, "_group"))
    inner = getattr(owner, name, None)
    if inner is not None:
        def timed_group(*args):
            t = time.perf_counter()
            inner(*args)
            groups.append(time.perf_counter() - t)

        setattr(owner, name, timed_group)
    t0 = time.perf_counter()
    traj = tracker.track(seq)
    wall = time.perf_counter() - t0
    span = (int(traj.t_us[-1]) - int(traj.t_us[0])) * 1e-6 if len(traj) > 1 else float("nan")
    st = tracker.stats
    times = dict(getattr(st, "time_s", {}))
    filt = times.get("velocity", 0.0) + times.get("pose", 0.0)
    digest = hashlib.sha1()
    for part in (traj.t_us, traj.poses, traj.twists, traj.status):
        digest.update(part.detach().cpu().contiguous().numpy().tobytes())
    row = {"sequence": Path(job["sequence"]).name, "method": cfg.method, "threads": threads,
           "size": f"{seq.meta.event_camera.width}x{seq.meta.event_camera.height}",
           "roi": cfg.flow.roi_size, "margin": cfg.mask_margin_px,
           "batch": cfg.flow_batch_steps, "pose_hz": cfg.pose_rate_hz,
           "cap": _option(cfg, "load", "max_events_per_step"),
           "sample": _option(cfg, "load", "search_per_roi_window"),
           "budget": _option(cfg, "load", "max_searched_per_step"),
           "unsearched": getattr(st, "events_unsearched", 0),
           "rt": _option(cfg, "load", "realtime", flat="realtime_load"),
           "budget_min": getattr(st, "search_budget_min", 0),
           "events_min": getattr(st, "event_budget_min", 0),
           "async": "on" if cfg.pose_async else "off",
           "prior": "on" if cfg.pose_prior else "off",
           "pose_src": times.get("pose_source", 0.0),
           "thinned": getattr(st, "events_thinned", 0), "source": source_name,
           "events": st.events,
           "seq_s": span, "proc_s": wall, "rtf": wall / span, "ev_per_s": st.events / wall,
           "flow": times.get("flow", 0.0), "velocity": times.get("velocity", 0.0),
           "pose": times.get("pose", 0.0),
           "frames": times.get("frames", 0.0),
           "group_p50_ms": 1e3 * statistics.median(groups) if groups else float("nan"),
           "group_p95_ms": 1e3 * float(np.quantile(groups, 0.95)) if groups else float("nan"),
           "step_us": 1e6 * filt / max(st.steps, 1), "traj": digest.hexdigest()[:12],
           "config": _flat(cfg.to_dict()) if hasattr(cfg, "to_dict") else {}}
    if seq.ground_truth is not None:
        from evtrack.eval.metrics import tracking_errors

        err = tracking_errors(traj, seq.ground_truth)
        row["error"] = f"{err.position_rmse_cm:.2f} cm {err.rotation_rmse_deg:.2f} deg"
    return _plain(row)


def _worker() -> int:
    """A child's loop: one JSON job per stdin line, one JSON reply per line on the original
    stdout (anything else the process prints goes to stderr)."""
    import traceback

    replies = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)

    def reply(obj: dict) -> None:
        replies.write(json.dumps(obj) + "\n")
        replies.flush()

    reply({"result": {"evtrack": str(Path(evtrack.__file__).resolve().parent),
                      "torch": torch.__version__,
                      "wait_policy": os.environ.get("OMP_WAIT_POLICY", "default")}})
    for line in sys.stdin:
        try:
            reply({"result": measure(json.loads(line))})
        except Exception:  # the parent reports it and stops
            reply({"error": traceback.format_exc()})
    return 0


# ----------------------------------------------------------------------------- runners
class InProcess:
    """Runs the measurements in this process (no ``--baseline``)."""

    def __init__(self) -> None:
        self.info = {"evtrack": str(Path(evtrack.__file__).resolve().parent),
                     "torch": torch.__version__,
                     "wait_policy": os.environ.get("OMP_WAIT_POLICY", "default")}

    def run(self, job: dict) -> dict:
        return measure(job)

    def close(self) -> None:
        pass


class Worker:
    """A child process running :func:`measure` on this script with the package found first on
    ``pythonpath`` (``None``: as this process finds it)."""

    def __init__(self, code: str, pythonpath: Path | None = None) -> None:
        self.code = code
        env = dict(os.environ)
        if pythonpath is not None:
            env["PYTHONPATH"] = os.pathsep.join(
                [str(pythonpath)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env,
                                     text=True)
        self.info = self._read()

    def _read(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            rc = self.proc.wait()
            raise RuntimeError(f"the {self.code} tree's child process exited with status {rc} "
                               "(its messages are above)")
        reply = json.loads(line)
        if "error" in reply:
            raise RuntimeError(f"the {self.code} tree's run failed:\n{reply['error']}")
        return reply["result"]

    def run(self, job: dict) -> dict:
        self.proc.stdin.write(json.dumps(job) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


# ----------------------------------------------------------------------------- planning
def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def short_commit() -> str:
    """The checkout's short commit hash, for a table's heading ("unknown" outside git)."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True, cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run_order(codes: list[str], index: int) -> list[str]:
    """The order of the trees in the ``index``-th round: reversed every other round."""
    return list(codes) if index % 2 == 0 else list(reversed(codes))


def combos(args: argparse.Namespace) -> list[dict]:
    """The settings of the rows (before the sequences): threads, options, method."""
    return [{"threads": th, "cap": cap, "sample": sample, "budget": budget, "rt": rt,
             "async": mode, "prior": prior, "method": m}
            for th in args.threads for cap in args.caps for sample in args.search_per_window
            for budget in args.search_budget for rt in args.realtime_load
            for mode in args.pose_async for prior in args.pose_prior for m in args.methods]


def config_changes(base: dict, combo: dict) -> dict:
    """``TrackerConfig.from_dict`` changes of a row: ``base`` and the row's options (those
    given; the others keep each tree's defaults)."""
    changes = {**base, "method": combo["method"], "torch_threads": combo["threads"]}
    for key, field in (("async", "pose_async"), ("prior", "pose_prior"),
                       ("cap", "max_events_per_step"), ("sample", "search_per_roi_window"),
                       ("budget", "max_searched_per_step"), ("rt", "realtime_load")):
        if combo[key] is not None:
            changes[field] = combo[key] == "on" if key in ("async", "prior") else combo[key]
    return changes


def combo_label(combo: dict) -> str:
    """The row's method and the options given for it."""
    names = {"cap": "cap", "sample": "sample", "budget": "budget", "rt": "rt",
             "async": "async", "prior": "prior"}
    extra = [f"{name}={combo[key]}" for key, name in names.items() if combo[key] is not None]
    return " ".join([combo["method"], *extra])


def median_row(runs: list[dict]) -> dict:
    """One row of several runs: the medians of the numbers, the first run's other fields,
    ``runs`` the processing times and ``trajs`` the trajectory digests."""
    row = dict(runs[0])
    for key, value in runs[0].items():
        if isinstance(value, float) and not isinstance(value, bool):
            row[key] = statistics.median(r[key] for r in runs)
    row["runs"] = [r["proc_s"] for r in runs]
    row["trajs"] = sorted({r["traj"] for r in runs})
    return row


def ratio_summary(pairs: list[tuple[float, float]]) -> str:
    """The new/old processing times of the rows: geometric mean, range, totals."""
    ratios = [n / o for o, n in pairs if o > 0]
    if not ratios:
        return "new/old: no rows"
    gmean = math.exp(sum(math.log(r) for r in ratios) / len(ratios))
    return (f"new/old processing time: geometric mean {gmean:.3f} over {len(ratios)} rows "
            f"(min {min(ratios):.3f}, max {max(ratios):.3f}); total old "
            f"{sum(o for o, _ in pairs):.2f} s, new {sum(n for _, n in pairs):.2f} s")


def config_differences(old: dict, new: dict) -> list[str]:
    """The configuration fields that differ between the trees' effective configs."""
    keys = sorted(set(old) | set(new))
    return [f"{k}: {old.get(k, '(absent)')} -> {new.get(k, '(absent)')}"
            for k in keys if old.get(k, "(absent)") != new.get(k, "(absent)")]


def _reference(argv: list[str] | None, new_where: str, old: str | None) -> None:
    command = shlex.join(["python", *(sys.argv if argv is None else [sys.argv[0], *argv])])
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(f"reference: {command}")
    print(f"  {now}, {cpu_model()} ({os.cpu_count()} CPUs), Python {platform.python_version()}, "
          f"torch {torch.__version__}")
    print(f"  new: {new_where}")
    if old is not None:
        print(f"  old: {old}", flush=True)


# ----------------------------------------------------------------------------- main
def _parser() -> argparse.ArgumentParser:
    head, _, rest = __doc__.partition("\n\n")
    ap = argparse.ArgumentParser(description=head.replace("\n", " "), epilog=rest,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    what = ap.add_mutually_exclusive_group()
    what.add_argument("--sequence", type=Path,
                      help="a sequence folder (default: simulate one); oracle poses unless "
                           "--weights (loaded as `evtrack track` loads them)")
    what.add_argument("--sequences", type=Path, nargs="+", metavar="DIR",
                      help="several sequence folders, tracked as `evtrack evaluate` tracks "
                           "them: the tracker's defaults, the shipped pose network of each "
                           "sequence's object (or --weights, or --oracle)")
    what.add_argument("--benchmark", type=Path, metavar="SETDIR",
                      help="a benchmark set (a folder of sequence folders, e.g. from `evtrack "
                           "simulate-benchmark`): its sequences of --speed, as --sequences")
    ap.add_argument("--speed", default="faster",
                    help="with --benchmark: the sequences of this speed label ('faster', "
                         "'regular'...; 'all': every sequence; default: faster)")
    ap.add_argument("--oracle", action="store_true",
                    help="oracle poses (ground truth + 1 cm / 0.03 rad noise per axis, seed 0, "
                         "as `evtrack evaluate --oracle`) instead of a pose network")
    ap.add_argument("--baseline", metavar="REV",
                    help="also run every row with the tracker of git revision REV (e.g. a "
                         "commit before a change), old and new each in a child process, "
                         "alternating, and print both with the ratio new/old")
    ap.add_argument("--new", metavar="REV",
                    help="the new side from git revision REV, exported as --baseline's, "
                         "instead of the package as installed (the working tree)")
    ap.add_argument("--export-dir", type=Path, metavar="DIR",
                    help="export the revisions of --baseline and --new into DIR/<commit> and "
                         "keep them (reused by later runs, with their compiled-kernel caches: "
                         "the first run of a fresh export compiles the numba kernels; "
                         "default: a temporary folder, removed at the end)")
    ap.add_argument("--repeats", type=int, default=1, metavar="N",
                    help="timed runs per row (and per tree), their median printed (default 1)")
    ap.add_argument("--warmup", action=argparse.BooleanOptionalAction, default=True,
                    help="track each method once untimed (on the first sequence) in each "
                         "process before its timed runs: the first run loads or compiles the "
                         "numba kernels (default: on)")
    ap.add_argument("--size", default="320x240", help="simulated image size WxH")
    ap.add_argument("--duration", type=float, default=None, metavar="S",
                    help="simulated seconds (default 1.0); with --sequence, --sequences or "
                         "--benchmark: track the first S seconds of each (default: all)")
    ap.add_argument("--threads", type=int, nargs="+", default=[2, 1],
                    help="torch (and compiled-kernel) thread counts to compare (default: 2 1)")
    ap.add_argument("--methods", nargs="+", default=["full", "pose"],
                    help="tracking methods to compare (default: full pose)")
    ap.add_argument("--roi-size", type=int, default=None,
                    help="flow RoI size (default: with a given sequence the tracker's, 12 px, "
                         "as `evtrack evaluate` runs it; on the simulated sequence the demo's, "
                         "32 px at 640 px, scaled)")
    ap.add_argument("--batch-steps", type=int, default=None, metavar="N",
                    help="flow_batch_steps: velocity steps per flow call (default: the "
                         "tracker's)")
    ap.add_argument("--mask-margin", type=float, default=None, metavar="PX",
                    help="mask_margin_px (default: the tracker's; on the simulated sequence "
                         "scaled to its width)")
    ap.add_argument("--weights", help="pose-network weights, .pt (torch) or .onnx "
                                      "(onnxruntime); with --sequences or --benchmark one file "
                                      "for every sequence (default: the oracle with a single "
                                      "or simulated sequence, else the shipped networks)")
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
                    help="TrackerConfig.load.realtime values to compare (the search and event "
                         "budgets follow the processing load, live use; 0: off, the default)")
    ap.add_argument("--pose-async", nargs="+", choices=["on", "off"], default=[None],
                    help="TrackerConfig.pose_async values to compare (on: the pose source in "
                         "the tracker's worker thread; default: the config's, on)")
    ap.add_argument("--pose-prior", nargs="+", choices=["on", "off"], default=[None],
                    help="TrackerConfig.pose_prior values to compare (on: the network looks "
                         "around the track's pose first; default: the config's)")
    ap.add_argument("--save-sequence", type=Path, metavar="DIR",
                    help="keep the simulated sequence in DIR (reuse it with --sequence DIR/seq)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    return ap


def check_arguments(ap: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``ap.error`` (exits) on options that do not go together or values out of range."""
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    if min(args.threads) < 1:
        ap.error(f"--threads must be >= 1, got {args.threads}")
    if args.duration is not None and not args.duration > 0:
        ap.error(f"--duration must be > 0, got {args.duration}")
    if args.oracle and args.weights:
        ap.error("--oracle and --weights exclude each other")
    if args.speed != "faster" and args.benchmark is None:
        ap.error("--speed selects the sequences of --benchmark")
    if args.export_dir is not None and args.baseline is None and args.new is None:
        ap.error("--export-dir needs --baseline or --new")
    if args.save_sequence is not None and (args.sequence or args.sequences or args.benchmark):
        ap.error("--save-sequence keeps the simulated sequence; not with given sequences")


def _sequence_list(args: argparse.Namespace) -> list[Path]:
    if args.sequences:
        return [p.resolve() for p in args.sequences]
    from evtrack.eval.sequences import find_sequences

    found = find_sequences(args.benchmark)
    chosen = [s.path.resolve() for s in found if args.speed in ("all", s.speed)]
    if not chosen:
        raise SystemExit(f"{args.benchmark}: no sequence of speed {args.speed!r} (speeds there: "
                         f"{sorted({s.speed for s in found})})")
    return chosen


def _pose_jobs(args: argparse.Namespace, folders: list[Path], several: bool) -> list[dict]:
    """The pose source of each sequence (the same in both trees: weights resolved here)."""
    if not several:
        return [{"loader": "track", "weights": None if args.oracle else args.weights}
                for _ in folders]
    if args.oracle:
        return [{"loader": "evaluate", "weights": None} for _ in folders]
    from evtrack.eval.pose_setup import PoseSourceSpec, resolve_weights

    names = [Sequence.load(f).meta.object_name for f in folders]
    weights = resolve_weights(PoseSourceSpec("network", weights=args.weights), names)
    return [{"loader": "evaluate", "weights": str(Path(weights[n]).resolve())} for n in names]


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    if args.worker:
        return _worker()
    check_arguments(ap, args)
    several = bool(args.sequences or args.benchmark)
    script_repo = Path(__file__).resolve().parent
    commits = {}
    for code, rev in (("old", args.baseline), ("new", args.new)):
        if rev is not None:
            try:
                commits[code] = resolve_revision(rev, script_repo)
            except RuntimeError:
                ap.error(f"--{'baseline' if code == 'old' else 'new'} {rev}: not a commit of "
                         f"the repository at {script_repo}")
    with tempfile.TemporaryDirectory(prefix="bench_tracker-") as tmp:
        if several:
            folders = _sequence_list(args)
        elif args.sequence is not None:
            folders = [args.sequence.resolve()]
        else:
            w, h = (int(v) for v in args.size.lower().split("x"))
            folders = [_simulate((w, h), args.duration or 1.0,
                                 args.save_sequence or Path(tmp)).resolve()]
        simulated = not several and args.sequence is None
        duration = None if simulated else args.duration
        base: dict = {}
        if simulated:  # the demo's pixel settings, scaled to the width (RoI 32 px at 640 px)
            from evtrack.demo import demo_tracker_config

            pixels = demo_tracker_config(Sequence.load(folders[0]).meta.event_camera.width)
            base = {"flow": {"roi_size": pixels.flow.roi_size},
                    "mask_margin_px": pixels.mask_margin_px}
        if args.roi_size is not None:
            base["flow"] = {"roi_size": args.roi_size}
        if args.mask_margin is not None:
            base["mask_margin_px"] = args.mask_margin
        if args.batch_steps is not None:
            base["flow_batch_steps"] = args.batch_steps
        poses = _pose_jobs(args, folders, several)

        codes = ["old", "new"] if "old" in commits else ["new"]
        runners: dict = {}
        try:
            where = _start_runners(args, commits, script_repo,
                                   args.export_dir.resolve() if args.export_dir else Path(tmp),
                                   runners)
            _reference(argv, where.get("new"), where.get("old"))
            table = _measure_all(args, runners, codes, folders, poses, base, duration)
        finally:
            for runner in runners.values():
                runner.close()
    _print_results(args, table, runners, codes, several, len(folders))
    return 0


def _start_runners(args: argparse.Namespace, commits: dict[str, str], repo: Path,
                   exports: Path, runners: dict) -> dict[str, str]:
    """Start the runner of each tree into ``runners`` (exporting the revisions of ``commits``
    under ``exports``); returns where each tree's code comes from, for the reference."""
    where = {}
    roots = {}
    for code, commit in commits.items():
        t0 = time.perf_counter()
        roots[code] = export_package(commit, repo, exports / commit[:12])
        print(f"{code} tree {commit[:12]} in {roots[code]} ({time.perf_counter() - t0:.1f} s)",
              file=sys.stderr)
        rev = args.baseline if code == "old" else args.new
        where[code] = (f"{commit[:12]} (--{'baseline' if code == 'old' else 'new'} {rev}), "
                       f"exported to {roots[code] / 'evtrack'}")
    if "old" not in commits and "new" not in commits:
        runners["new"] = InProcess()
    for code in ("old", "new"):
        if code in commits:
            runners[code] = Worker(code, roots[code])
            if Path(runners[code].info["evtrack"]) != (roots[code] / "evtrack").resolve():
                raise RuntimeError(f"the {code} tree's child imported "
                                   f"{runners[code].info['evtrack']}, not "
                                   f"{roots[code] / 'evtrack'}")
        elif code == "new" and "new" not in runners:
            runners["new"] = Worker("new")
            if any(Path(runners["new"].info["evtrack"]).is_relative_to(r)
                   for r in roots.values()):
                raise RuntimeError("the new tree's child imported an exported tree")
    if "new" not in commits:
        installed = Path(runners["new"].info["evtrack"])
        where["new"] = f"{tree_commit(installed)}, evtrack from {installed}"
    return where


def _measure_all(args, runners, codes, folders, poses, base, duration) -> list:
    """Every row, the trees alternating; ``[(label, {code: median row}, combo)]``."""
    settings = combos(args)
    warmed: set[tuple[str, str]] = set()
    table = []
    total = len(folders) * len(settings) * args.repeats * len(codes)
    done, rounds = 0, 0
    for folder, pose in zip(folders, poses, strict=True):
        for combo in settings:
            job = {"sequence": str(folder), "duration": duration, "threads": combo["threads"],
                   "config": config_changes(base, combo), "pose": pose}
            for code in codes:
                if args.warmup and (code, combo["method"]) not in warmed:
                    t0 = time.perf_counter()
                    runners[code].run({**job, "sequence": str(folders[0]), "pose": poses[0]})
                    warmed.add((code, combo["method"]))
                    print(f"warm-up {code} {combo['method']}: {time.perf_counter() - t0:.1f} s",
                          file=sys.stderr, flush=True)
            runs: dict[str, list[dict]] = {code: [] for code in codes}
            for _ in range(args.repeats):
                for code in run_order(codes, rounds):
                    row = runners[code].run(job)
                    runs[code].append(row)
                    done += 1
                    print(f"[{done}/{total}] {folder.name} {combo_label(combo)} "
                          f"{combo['threads']} thr {code}: {row['proc_s']:.2f} s",
                          file=sys.stderr, flush=True)
                rounds += 1
            table.append((combo_label(combo), {c: median_row(runs[c]) for c in codes}, combo))
    return table


def _print_results(args, table, runners, codes, several: bool, n_seq: int) -> None:
    first = table[0][1]["new"]
    what = (f"{n_seq} sequence{'s' if n_seq > 1 else ''}"
            + (f" of {args.benchmark} ({args.speed})" if args.benchmark else "")
            if several else f"{first['size']}, {first['events']} events over "
            f"{first['seq_s']:.2f} s")
    span = (f", the first {args.duration:g} s of {'each' if n_seq > 1 else 'it'}"
            if several and args.duration else "")
    source = first["source"] if not several or args.oracle or args.weights else (
        "the shipped network of each object")
    print(f"\nevtrack.Tracker speed: {what}{span}, RoI {first['roi']} px, mask margin "
          f"{first['margin']:g} px, pose source {source} at {first['pose_hz']:g} Hz, 1 ms "
          f"velocity steps, flow every {first['batch']} steps, OMP_WAIT_POLICY "
          f"{runners['new'].info['wait_policy']}"
          + (f", median of {args.repeats} runs" if args.repeats > 1 else ""))
    if "old" in codes:
        diffs = config_differences(table[0][1]["old"]["config"], first["config"])
        print("tracker configuration: the same in both trees" if not diffs
              else "tracker configuration, old -> new: " + "; ".join(diffs))
    if several or "old" in codes:
        print_compact([(label, rows, combo) for label, rows, combo in table], "old" in codes)
    else:
        print_wide([rows["new"] for _, rows, _ in table])
    print("rtf = processing time / sequence time; grp = one step group (one flow call): the "
          "output latency in live use" + ("" if several or "old" in codes else
                                            "; filt/step = velocity KF + pose UKF per 1 ms step")
          + ".")
    if "old" in codes:
        print(ratio_summary([(rows["old"]["proc_s"], rows["new"]["proc_s"])
                             for _, rows, _ in table]))


if __name__ == "__main__":
    raise SystemExit(main())
