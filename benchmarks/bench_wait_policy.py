"""The tracker's speed under OpenMP's wait policies, side by side (evtrack.runtime.openmp_wait).

    python benchmarks/bench_wait_policy.py --sequence DIR [DIR ...] [--repeats 2]
                                           [--method full] [--threads 2]

OpenMP reads ``OMP_WAIT_POLICY`` once, when torch loads it, so one process cannot compare
policies: each run is a fresh child process (``--child``), the policies interleaved run by
run so that the machine's load drifts over all of them alike. Per sequence and policy it
prints the median over the repeats of the processing time, the real-time factor (processing
time / sequence time) and the flow stage's share. ``default`` is the runtime's own setting
(torch imported before evtrack, the variable unset); ``PASSIVE`` is what ``import evtrack``
sets when it comes first.

Each child tracks the sequence twice and times the second run (the first loads the compiled
kernels). The pose source is the oracle (ground truth with 1 cm / 0.03 rad noise), as in
``benchmarks/bench_tracker.py``. Timings on a shared machine are noisy: use ``--repeats``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from tracker_runs import add_run_arguments, compare, run_child, time_tracking

POLICIES = ("default", "PASSIVE", "ACTIVE")


def _child(sequence: Path, method: str, threads: int) -> dict:
    """Track ``sequence`` in this process (its wait policy is the parent's choice)."""
    # torch first: the runtime reads the parent's setting; evtrack, loaded after it, leaves the
    # variable as it is (unset for "default")
    import torch  # noqa: F401

    return time_tracking(sequence, {"method": method}, threads)


def _spawn(sequence: Path, policy: str, method: str, threads: int) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy != "default":
        env["OMP_WAIT_POLICY"] = policy
    cmd = [sys.executable, __file__, "--child", "--sequence", str(sequence), "--policies", policy,
           "--method", method, "--threads", str(threads)]
    return run_child(cmd, f"{sequence}, {policy}", env)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policies", nargs="+", default=["default", "PASSIVE"], choices=POLICIES)
    add_run_arguments(ap, "policy")
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(_child(args.sequence[0], args.method, args.threads)))
        return 0
    print(f"evtrack.Tracker ({args.method}, {args.threads} threads, oracle poses) under OpenMP "
          f"wait policies; median of {args.repeats} interleaved runs, each a fresh process")
    compare(args.sequence, args.policies, "policy", args.repeats,
            lambda seq, name: _spawn(seq, name, args.method, args.threads))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
