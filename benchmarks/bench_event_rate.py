"""How the tracker's processing time grows with the event rate, and the rate it keeps up with.

    python benchmarks/bench_event_rate.py --sequence SET [DIR ...] [--repeats 2]
        [--frames files|memory] [--method full] [--threads 2]

Tracks each sequence (``--sequence SET`` takes every sequence folder of a set, e.g. the
output of ``evtrack simulate-benchmark --out SET``; or name the folders) with the tracker's
defaults and oracle poses (1 cm / 0.03 rad noise, 5 Hz, no network: the tracking's own cost),
``--repeats`` rounds of one fresh process per sequence, the sequences interleaved so that the
machine's load drifts over all of them alike. Each child tracks its sequence twice and times
the second run (the first loads the compiled kernels).

Printed per sequence: its events, the event rate (events / sequence time, Mev/s), the median
processing time and real-time factor (processing / sequence time; < 1: faster than real time)
and every run's time. Then the least-squares line through the sequences' points,

    rtf ~= fixed + per_mev * rate

(``fixed``: the real-time factor of the work every sequence has whatever its events: the
filters' steps, the pose source's calls and checks, the depth frames, the silhouettes;
``per_mev``: what each Mev/s of events adds), the event rate at which that line reaches
real time, ``(1 - fixed) / per_mev``, and each sequence's residual. The line is a summary,
not a law: above ``load.max_searched_per_step`` searched events per step the search and the
registration stop growing with the rate, so the dense sequences cost less per event than
the sparse ones.

Timings on a shared machine drift by 10-40 % between hours (steal time): compare rates only
within one invocation.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

from tracker_runs import check_run_arguments, run_child, time_tracking


def sequence_folders(paths: list[Path]) -> list[Path]:
    """The sequence folders (holding ``meta.yaml``) among ``paths``: each path itself, or,
    for a folder of sequences (a benchmark set), its sequence subfolders in name order.

    Raises:
        ValueError: a path that is neither.
    """
    found = []
    for path in paths:
        if (path / "meta.yaml").is_file():
            found.append(path)
            continue
        inner = (sorted(p for p in path.iterdir() if (p / "meta.yaml").is_file())
                 if path.is_dir() else [])
        if not inner:
            raise ValueError(f"{path}: not a sequence folder (no meta.yaml) nor a folder of "
                             "sequence folders")
        found += inner
    return list(dict.fromkeys(found))  # each once, in the order given


def event_count(sequence: Path) -> tuple[int, float]:
    """``(events, seconds from the first to the last event)`` of a sequence folder."""
    from evtrack.io import open_events
    from evtrack.sequence import EVENTS_FILE

    with open_events(sequence / EVENTS_FILE) as reader:
        n = reader.num_events
        t0, t1 = reader.t_start, reader.t_end
    if not n or t0 is None or t1 is None or t1 <= t0:
        raise ValueError(f"{sequence}: no events, or all at one time; nothing to rate")
    return n, (t1 - t0) * 1e-6


def fit_line(rates: list[float], rtfs: list[float]) -> tuple[float, float]:
    """Least-squares ``rtf = fixed + per_mev * rate``; needs two distinct rates."""
    mean_r, mean_f = statistics.fmean(rates), statistics.fmean(rtfs)
    var = sum((r - mean_r) ** 2 for r in rates)
    if var == 0.0:
        raise ValueError("the sequences' event rates are all equal: no line to fit")
    per_mev = sum((r - mean_r) * (f - mean_f) for r, f in zip(rates, rtfs, strict=True)) / var
    return mean_f - per_mev * mean_r, per_mev


def _spawn(sequence: Path, args: argparse.Namespace) -> dict:
    cmd = [sys.executable, __file__, "--child", "--sequence", str(sequence), "--method",
           args.method, "--threads", str(args.threads), "--frames", args.frames]
    return run_child(cmd, str(sequence))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, nargs="+", required=True,
                    help="sequence folders, or a folder of them (a set from evtrack "
                         "simulate-benchmark); at least two event rates for the line")
    ap.add_argument("--repeats", type=int, default=2, help="runs per sequence")
    ap.add_argument("--frames", choices=("files", "memory"), default="files",
                    help="RGB-D frames read while tracking (files, the default, as evaluate "
                         "runs) or decoded beforehand (memory, as a live camera gives them)")
    ap.add_argument("--method", default="full", help="tracker method")
    ap.add_argument("--threads", type=int, default=2, help="torch (and kernel) threads")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(time_tracking(args.sequence[0], {"method": args.method},
                                       args.threads, args.frames)))
        return 0
    check_run_arguments(ap, args)
    try:
        args.sequence = sequence_folders(args.sequence)
    except ValueError as exc:
        ap.error(str(exc))
    counts = {}
    for seq in args.sequence:
        try:
            counts[seq] = event_count(seq)
        except ValueError as exc:
            ap.error(str(exc))
    print(f"evtrack.Tracker ({args.method}, {args.threads} threads, oracle poses, frames "
          f"{'decoded beforehand' if args.frames == 'memory' else 'read while tracking'}); "
          f"median of {args.repeats} interleaved runs, each a fresh process", flush=True)
    runs: dict[Path, list[dict]] = {seq: [] for seq in args.sequence}
    for _ in range(args.repeats):
        for seq in args.sequence:
            runs[seq].append(_spawn(seq, args))
    line = (f"{'sequence':<32} {'events':>10} {'Mev/s':>6} {'proc s':>7} {'rtf':>6}"
            f"  runs (s)")
    print(line)
    print("-" * len(line))
    rates, rtfs = [], []
    for seq in args.sequence:
        n, span = counts[seq]
        proc = statistics.median(r["proc_s"] for r in runs[seq])
        rtf = statistics.median(r["rtf"] for r in runs[seq])
        rates.append(n / span * 1e-6)
        rtfs.append(rtf)
        print(f"{seq.name[:32]:<32} {n:>10} {rates[-1]:>6.2f} {proc:>7.2f} {rtf:>6.2f}  "
              + " ".join(f"{r['proc_s']:.2f}" for r in runs[seq]))
    if len(set(rates)) < 2:
        print("one event rate only: no line fitted")
        return 0
    fixed, per_mev = fit_line(rates, rtfs)
    print(f"\nrtf ~= {fixed:.2f} + {per_mev:.3f} per Mev/s (least squares over "
          f"{len(rates)} sequences)")
    if per_mev > 0 and fixed < 1:
        print(f"real time (rtf 1) up to ~{(1 - fixed) / per_mev:.1f} Mev/s on this machine")
    else:
        print("the line does not reach real time at any event rate on this machine")
    print("residuals (measured - line): " + ", ".join(
        f"{seq.name} {f - (fixed + per_mev * r):+.2f}"
        for seq, r, f in zip(args.sequence, rates, rtfs, strict=True)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
