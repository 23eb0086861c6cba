"""The tracker's speed under OpenMP's wait policies, side by side (evtrack.openmp_wait).

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
import statistics
import subprocess
import sys
import time
from pathlib import Path

POLICIES = ("default", "PASSIVE", "ACTIVE")


def _child(sequence: Path, method: str, threads: int) -> dict:
    """Track ``sequence`` in this process (its wait policy is the parent's choice)."""
    # torch first: the runtime reads the parent's setting; evtrack, loaded after it, leaves the
    # variable as it is (unset for "default")
    import torch

    from evtrack import Sequence
    from evtrack.pose_sources import OraclePoseSource
    from evtrack.tracker import Tracker
    from evtrack.tracking_config import TrackerConfig

    torch.set_num_threads(threads)
    seq = Sequence.load(sequence)
    cfg = TrackerConfig.from_dict({"method": method, "torch_threads": threads})
    result = {}
    for _ in range(2):  # the first run loads the compiled kernels
        source = OraclePoseSource.from_sequence(seq, std_translation=0.01, std_rotation=0.03)
        tracker = Tracker.for_sequence(seq, cfg, source)
        t0 = time.perf_counter()
        traj = tracker.track(seq)
        wall = time.perf_counter() - t0
        span = (int(traj.t_us[-1]) - int(traj.t_us[0])) * 1e-6
        result = {"proc_s": wall, "rtf": wall / span,
                  "flow_s": tracker.stats.time_s.get("flow", 0.0)}
    return result


def _spawn(sequence: Path, policy: str, method: str, threads: int) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy != "default":
        env["OMP_WAIT_POLICY"] = policy
    cmd = [sys.executable, __file__, "--child", "--sequence", str(sequence), "--policies", policy,
           "--method", method, "--threads", str(threads)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"child run on {sequence} ({policy}) failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, nargs="+", required=True,
                    help="sequence folders with ground truth (evtrack simulate-benchmark)")
    ap.add_argument("--policies", nargs="+", default=["default", "PASSIVE"], choices=POLICIES)
    ap.add_argument("--repeats", type=int, default=2, help="runs per sequence and policy")
    ap.add_argument("--method", default="full", help="tracker method")
    ap.add_argument("--threads", type=int, default=2, help="torch (and kernel) threads")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(_child(args.sequence[0], args.method, args.threads)))
        return 0
    print(f"evtrack.Tracker ({args.method}, {args.threads} threads, oracle poses) under OpenMP "
          f"wait policies; median of {args.repeats} interleaved runs, each a fresh process")
    head = f"{'sequence':<32} {'policy':<8} {'proc s':>7} {'rtf':>6} {'flow s':>7}  runs (s)"
    print(head)
    print("-" * len(head))
    for seq in args.sequence:
        runs: dict[str, list[dict]] = {p: [] for p in args.policies}
        for _ in range(args.repeats):
            for policy in args.policies:
                runs[policy].append(_spawn(seq, policy, args.method, args.threads))
        for policy, rs in runs.items():
            med = {k: statistics.median(r[k] for r in rs) for k in ("proc_s", "rtf", "flow_s")}
            print(f"{seq.name[:32]:<32} {policy:<8} {med['proc_s']:>7.2f} {med['rtf']:>6.2f} "
                  f"{med['flow_s']:>7.2f}  " + " ".join(f"{r['proc_s']:.2f}" for r in rs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
