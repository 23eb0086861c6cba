"""The tracker's CPU-side speed-ups, each against the code without it, side by side.

    python benchmarks/bench_tracker_cpu.py --sequence DIR [DIR ...] [--repeats 2]
                                           [--variants reference blas strips mask]

Variants, cumulative (each adds one change to the one before):

* ``reference``: numpy's BLAS on its own threads (``blas_threads: 0``), the flow's candidate
  search in one loop (no strips), the event mask by the half-plane point test
  (:func:`evtrack.silhouette.points_in_polygon`, a (N, edges) product);
* ``blas``: numpy's BLAS on one thread while tracking (:mod:`evtrack.blas_threads`): OpenBLAS's
  idle workers no longer spin after the mask's product;
* ``strips``: the search split into horizontal strips of the sensor, one per thread
  (:class:`evtrack.flow.compiled.CompiledSearch`);
* ``mask``: the event mask by row spans (:func:`evtrack.silhouette.pixels_in_polygon`), the
  tracker's default: all three changes.

Every variant gives the same trajectory up to float rounding (the strips bit for bit; the
BLAS thread count and the mask's arithmetic can move an event on the mask's edge). Each run
is a fresh child process, the variants interleaved run by run so that the machine's load
drifts over all alike; each child tracks the sequence twice and times the second run (the
first loads the compiled kernels). Oracle poses (1 cm / 0.03 rad noise), as in
``benchmarks/bench_tracker.py``. Printed per sequence and variant: the median processing time,
the real-time factor (processing / sequence time) and the flow stage's time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

VARIANTS = ("reference", "blas", "strips", "mask")


def _child(sequence: Path, variant: str, method: str, threads: int) -> dict:
    # first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.openmp_wait)
    import evtrack  # noqa: F401  # isort: skip
    import torch

    from evtrack import Sequence
    from evtrack.flow.compiled import CompiledSearch
    from evtrack.pose_sources import OraclePoseSource
    from evtrack.silhouette import SilhouettePolygon
    from evtrack.tracker import Tracker
    from evtrack.tracking_config import TrackerConfig

    level = VARIANTS.index(variant)
    if level < VARIANTS.index("strips"):
        CompiledSearch.parallel_min_events = 1 << 62
    if level < VARIANTS.index("mask"):
        def point_test(self, x, y, margin, size):
            import numpy as np

            xy = np.stack([x, y], 1).astype(np.float64)
            # the reference: one (N, 2) @ (2, edges) product, as the tracker had it
            poly = np.asarray(self.vertices, np.float64)
            edges = np.roll(poly, -1, axis=0) - poly
            nxt = np.roll(poly, -1, axis=0)
            area2 = float(np.sum(poly[:, 0] * nxt[:, 1] - nxt[:, 0] * poly[:, 1]))
            normals = np.stack([edges[:, 1], -edges[:, 0]], 1) * (1.0 if area2 > 0 else -1.0)
            length = np.linalg.norm(normals, axis=1)
            keep = length > 0
            normals = normals[keep] / length[keep, None]
            offsets = np.einsum("kd,kd->k", normals, poly[keep])
            return (xy @ normals.T - offsets).max(axis=1) <= margin

        SilhouettePolygon.contains_pixels = point_test
    torch.set_num_threads(threads)
    seq = Sequence.load(sequence)
    cfg = TrackerConfig.from_dict({"method": method, "torch_threads": threads,
                                   "blas_threads": 0 if level < 1 else 1})
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


def _spawn(sequence: Path, variant: str, method: str, threads: int) -> dict:
    cmd = [sys.executable, __file__, "--child", "--sequence", str(sequence), "--variants",
           variant, "--method", method, "--threads", str(threads)]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"child run on {sequence} ({variant}) failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sequence", type=Path, nargs="+", required=True,
                    help="sequence folders (e.g. from evtrack simulate-benchmark)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS,
                    help="which cumulative variants to run (default: all)")
    ap.add_argument("--repeats", type=int, default=2, help="runs per sequence and variant")
    ap.add_argument("--method", default="full", help="tracker method")
    ap.add_argument("--threads", type=int, default=2, help="torch (and kernel) threads")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(_child(args.sequence[0], args.variants[0], args.method, args.threads)))
        return 0
    print(f"evtrack.Tracker ({args.method}, {args.threads} threads, oracle poses), cumulative "
          f"CPU changes; median of {args.repeats} interleaved runs, each a fresh process")
    head = f"{'sequence':<32} {'variant':<10} {'proc s':>7} {'rtf':>6} {'flow s':>7}  runs (s)"
    print(head)
    print("-" * len(head))
    for seq in args.sequence:
        runs: dict[str, list[dict]] = {v: [] for v in args.variants}
        for _ in range(args.repeats):
            for variant in args.variants:
                runs[variant].append(_spawn(seq, variant, args.method, args.threads))
        for variant, rs in runs.items():
            med = {k: statistics.median(r[k] for r in rs) for k in ("proc_s", "rtf", "flow_s")}
            print(f"{seq.name[:32]:<32} {variant:<10} {med['proc_s']:>7.2f} {med['rtf']:>6.2f} "
                  f"{med['flow_s']:>7.2f}  " + " ".join(f"{r['proc_s']:.2f}" for r in rs),
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
