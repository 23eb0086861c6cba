"""Wall and CPU time of ``evtrack demo`` per stage, against its 5-minute budget on 2 CPU cores.

    python benchmarks/bench_evaluate.py [--size 320x240] [--duration 1.5] [--jobs 1 2]
                                        [--weights W.pt]

Runs the demo (simulate, track velocity/pose/full, tables, plots, video) once per ``--jobs``
value in this process, side by side, with the oracle pose source unless ``--weights`` is given.
CPU time includes the worker processes (``--jobs`` > 1). On a machine shared with other work
the wall times are noisy (the load average is printed); the CPU times are not, and their sum
bounds the wall time on one free core.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

from evtrack.demo import DemoOptions, run_demo

BUDGET_S = 300.0


def _cpu() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _run(size, duration, jobs, weights, root: Path) -> dict:
    stages: dict[str, tuple[float, float]] = {}
    marks = [("start", time.perf_counter(), _cpu())]

    def log(line: str) -> None:
        marks.append((line.split("]")[0].strip("["), time.perf_counter(), _cpu()))

    opts = DemoOptions(out=root / f"demo_j{jobs}", duration=duration, size=size,
                       weights=weights, oracle=weights is None, jobs=jobs, progress=False)
    res = run_demo(opts, log=log)
    marks.append(("end", time.perf_counter(), _cpu()))
    names = ["simulate", "track", "report"]
    for name, (_, w0, c0), (_, w1, c1) in zip(names, marks[1:-1], marks[2:], strict=True):
        stages[name] = (w1 - w0, c1 - c0)
    total = (marks[-1][1] - marks[0][1], marks[-1][2] - marks[0][2])
    errors = {r.run: r.errors for r in res.results}
    return {"jobs": jobs, "stages": stages, "total": total, "errors": errors}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="320x240", help="camera size WxH (demo default)")
    ap.add_argument("--duration", type=float, default=1.5, help="seconds (demo default)")
    ap.add_argument("--jobs", type=int, nargs="+", default=[2, 1])
    ap.add_argument("--weights", type=Path, default=None,
                    help="pose-network weights for 'box' (default: the oracle)")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        rows = [_run(size, args.duration, j, args.weights, Path(tmp)) for j in args.jobs]
    load1 = os.getloadavg()[0]
    print(f"\nevtrack demo: {size[0]}x{size[1]}, {args.duration:g} s, pose source "
          f"{'oracle' if args.weights is None else args.weights.name}; load average "
          f"{load0:.1f} -> {load1:.1f} on {os.cpu_count()} CPUs")
    head = (f"{'jobs':>4}  {'simulate':>15}  {'track':>15}  {'report':>15}  {'total':>15}  "
            f"{'budget':>6}   wall/CPU seconds")
    print(head)
    print("-" * len(head))
    for r in rows:
        cells = [f"{w:6.1f} / {c:6.1f}" for w, c in (*r["stages"].values(), r["total"])]
        ok = "ok" if r["total"][0] < BUDGET_S else "OVER"
        print(f"{r['jobs']:>4}  " + "  ".join(f"{c:>15}" for c in cells) + f"  {ok:>6}")
    for r in rows[:1]:
        for run, e in r["errors"].items():
            print(f"  {run:<9} {e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
