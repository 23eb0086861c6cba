"""Helpers of the tracker benchmarks that compare settings in fresh child processes
(``bench_wait_policy.py``, ``bench_tracker_cpu.py``). Nothing is imported at module level:
a child decides what loads first (torch before evtrack, or the reverse)."""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

FIELDS = ("proc_s", "rtf", "flow_s")


def time_tracking(sequence: Path, config: dict, threads: int, frames: str = "files") -> dict:
    """Track ``sequence`` twice in this process and time the second run (the first loads the
    compiled kernels). Oracle poses (1 cm / 0.03 rad noise), as in ``bench_tracker.py``.

    Args:
        frames: ``"files"``: the tracker reads and decodes the RGB and depth frames from the
            sequence's image files as it goes (``Tracker.track`` on a recording); ``"memory"``:
            every frame is decoded before the timed runs, as a live RGB-D camera delivers
            them (the tracking alone).

    Returns:
        ``{"proc_s": s, "rtf": processing / sequence time, "flow_s": the flow stage's s}``.
    """
    import torch

    from evtrack import Sequence
    from evtrack.tracking.config import TrackerConfig
    from evtrack.tracking.pose_sources import OraclePoseSource
    from evtrack.tracking.tracker import Tracker

    torch.set_num_threads(threads)
    seq = Sequence.load(sequence)
    if frames == "memory":
        depth = [seq.depth(i) for i in range(len(seq.depth_times_us))]
        rgb = [seq.rgb(i) for i in range(len(seq.rgb_times_us))]
        seq.depth, seq.rgb = depth.__getitem__, rgb.__getitem__
    elif frames != "files":
        raise ValueError(f"frames must be 'files' or 'memory', got {frames!r}")
    cfg = TrackerConfig.from_dict({**config, "torch_threads": threads})
    result = {}
    for _ in range(2):
        source = OraclePoseSource.from_sequence(seq, std_translation=0.01, std_rotation=0.03)
        tracker = Tracker.for_sequence(seq, cfg, source)
        t0 = time.perf_counter()
        traj = tracker.track(seq)
        wall = time.perf_counter() - t0
        span = (int(traj.t_us[-1]) - int(traj.t_us[0])) * 1e-6
        result = {"proc_s": wall, "rtf": wall / span,
                  "flow_s": tracker.stats.time_s.get("flow", 0.0)}
    return result


def run_child(cmd: list[str], what: str, env: dict | None = None) -> dict:
    """Run a child benchmark process; its last stdout line is the JSON result."""
    out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"child run ({what}) failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def header(label: str) -> None:
    """The table's header; ``label`` names the compared setting."""
    line = f"{'sequence':<32} {label:<16} {'proc s':>7} {'rtf':>6} {'flow s':>7}  runs (s)"
    print(line)
    print("-" * len(line))


def print_medians(sequence: Path, runs: dict[str, list[dict]]) -> None:
    """One row per setting: the medians of its runs and each run's processing time."""
    for name, rs in runs.items():
        med = {k: statistics.median(r[k] for r in rs) for k in FIELDS}
        print(f"{sequence.name[:32]:<32} {name:<16} {med['proc_s']:>7.2f} {med['rtf']:>6.2f} "
              f"{med['flow_s']:>7.2f}  " + " ".join(f"{r['proc_s']:.2f}" for r in rs),
              flush=True)


def add_run_arguments(ap: argparse.ArgumentParser, what: str) -> None:
    """The arguments both benchmarks take (``what``: the name of the compared setting)."""
    ap.add_argument("--sequence", type=Path, nargs="+", required=True,
                    help="sequence folders (e.g. from evtrack simulate-benchmark)")
    ap.add_argument("--repeats", type=int, default=2, help=f"runs per sequence and {what}")
    ap.add_argument("--method", default="full", help="tracker method")
    ap.add_argument("--threads", type=int, default=2, help="torch (and kernel) threads")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)


def check_run_arguments(ap: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``ap.error`` (exits) on ``--repeats`` or ``--threads`` below 1 or a ``--method`` the
    tracker does not have."""
    if args.repeats < 1:
        ap.error(f"--repeats must be >= 1, got {args.repeats}")
    if args.threads < 1:
        ap.error(f"--threads must be >= 1, got {args.threads}")
    from evtrack.errors import ConfigError
    from evtrack.tracking.config import TrackerConfig

    try:
        TrackerConfig.from_dict({"method": args.method})
    except ConfigError as exc:
        ap.error(f"--method: {exc}")


def compare(sequences: list[Path], settings: list[str], label: str, repeats: int,
            spawn: Callable[[Path, str], dict]) -> None:
    """Per sequence, ``repeats`` rounds of one fresh run per setting (interleaved, so that the
    machine's load drifts over all alike), then the table of medians."""
    header(label)
    for seq in sequences:
        runs: dict[str, list[dict]] = {name: [] for name in settings}
        for _ in range(repeats):
            for name in settings:
                runs[name].append(spawn(seq, name))
        print_medians(seq, runs)
