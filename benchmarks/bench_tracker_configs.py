"""Tracking errors and speed of tracker configs side by side, with oracle poses.

    python benchmarks/bench_tracker_configs.py --sequence DIR [DIR ...]
        [--config configs/tracker_slow.yaml ...] [--seeds 0 1 2] [--method full]

Every sequence is tracked with the tracker's defaults (``configs/tracker.yaml``) and with
each ``--config`` (files with only the fields they change, as ``TrackerConfig.from_yaml``
reads them), once per oracle seed: the pose source is the ground truth with 1 cm / 0.03 rad
noise per axis at 5 Hz and 200 ms latency (the ``evtrack evaluate --oracle`` setting), so the
differences are those of the event side (flow, velocity filter) between two poses. Prints one
line per sequence, config and seed (RMSE of position and rotation, tracked samples, wall
time, the flow stage's time) and the means per preset (``regular``, ``faster``: the folder
name's suffix) and config, averaged over the seeds. 2 torch threads, as the speed target.

The sequences: ``evtrack simulate-benchmark --out DIR`` (four YCB objects x regular, faster).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

# first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.runtime.openmp_wait)
import evtrack  # noqa: F401  # isort: skip
import torch

ROOT = Path(__file__).resolve().parents[1]


def _run(sequence, config, seed: int, method: str) -> dict:
    from evtrack.eval.metrics import tracking_errors
    from evtrack.tracking.pose_sources import OraclePoseSource
    from evtrack.tracking.tracker import Tracker

    source = OraclePoseSource.from_sequence(sequence, std_translation=0.01,
                                            std_rotation=0.03, seed=seed)
    tracker = Tracker.for_sequence(sequence, config.replace(method=method), source)
    t0 = time.perf_counter()
    trajectory = tracker.track(sequence)
    wall = time.perf_counter() - t0
    err = tracking_errors(trajectory, sequence.ground_truth)
    return {"pos": err.position_rmse_cm, "rot": err.rotation_rmse_deg, "tracked": err.samples,
            "total": err.total, "wall": wall, "flow": tracker.stats.time_s.get("flow", 0.0)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequence", type=Path, nargs="+", required=True,
                    help="sequence folders (names ending in _regular / _faster are averaged "
                         "per preset)")
    ap.add_argument("--config", type=Path, nargs="*", default=[ROOT / "configs/tracker_slow.yaml"],
                    help="tracker config YAMLs compared with the defaults "
                         "(default: configs/tracker_slow.yaml)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="oracle noise seeds (each a run per sequence and config)")
    ap.add_argument("--method", default="full", help="tracker method")
    ap.add_argument("--threads", type=int, default=2, help="torch (and kernel) threads")
    args = ap.parse_args(argv)

    from evtrack import Sequence
    from evtrack.tracking.config import TrackerConfig

    torch.set_num_threads(args.threads)
    configs = {"defaults": TrackerConfig.from_dict({"torch_threads": args.threads})}
    for path in args.config:
        configs[path.stem] = TrackerConfig.from_yaml(path).replace(torch_threads=args.threads)
    print(f"{args.method}, oracle poses (1 cm / 0.03 rad) at 5 Hz, {args.threads} threads, "
          f"seeds {args.seeds}")
    head = (f"{'sequence':<30} {'config':<16} {'seed':>4} {'pos cm':>7} {'rot deg':>8} "
            f"{'tracked':>10} {'wall s':>7} {'flow s':>7}")
    print(head)
    print("-" * len(head))
    # one untimed run first: it loads the compiled kernels (the wall times below are warm)
    _run(Sequence.load(args.sequence[0]), configs["defaults"], args.seeds[0], args.method)
    rows: dict[tuple[str, str], list[dict]] = {}
    for folder in args.sequence:
        sequence = Sequence.load(folder)
        preset = folder.name.rsplit("_", 1)[-1]
        for name, config in configs.items():
            for seed in args.seeds:
                r = _run(sequence, config, seed, args.method)
                rows.setdefault((preset, name), []).append(r)
                print(f"{folder.name[:30]:<30} {name:<16} {seed:>4} {r['pos']:>7.2f} "
                      f"{r['rot']:>8.2f} {r['tracked']:>5}/{r['total']:<4} {r['wall']:>7.2f} "
                      f"{r['flow']:>7.2f}", flush=True)
    print("\nmeans over sequences and seeds")
    print(f"{'preset':<10} {'config':<16} {'pos cm':>7} {'rot deg':>8} {'wall s':>7}")
    for (preset, name), rs in sorted(rows.items()):
        print(f"{preset:<10} {name:<16} {statistics.mean(r['pos'] for r in rs):>7.2f} "
              f"{statistics.mean(r['rot'] for r in rs):>8.2f} "
              f"{statistics.mean(r['wall'] for r in rs):>7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
