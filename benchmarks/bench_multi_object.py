"""What tracking several objects from one stream costs, against one object at the same number
of events.

    python benchmarks/bench_multi_object.py --multi SEQ [SEQ ...] --single SEQ [SEQ ...]
        [--threads N] [--repeats R] [--config tracker.yaml]

* ``--multi``: sequences with several objects (``evtrack simulate-benchmark --multi-object``):
  every object tracked by one :class:`evtrack.tracking.multi.MultiTracker`;
* ``--single``: one-object sequences (e.g. the fixed benchmark set): one
  :class:`evtrack.Tracker` each.

Every run uses the oracle pose source (ground truth + noise, the ``evaluate --oracle``
settings) so that the rows measure the tracker and not a pose network (a network costs one
call per object and frame on top). For each multi-object sequence the reference is the
one-object sequence whose event count is nearest, its time scaled to the multi-object
sequence's events (``t_1 x E_multi / E_1``): the ratio ``t_multi / that`` is the cost of
tracking K objects against one at the same total number of events. All runs happen in this
process with ``--threads`` torch threads (default 1); each multi-object sequence and its
reference run in turn, ``--repeats`` times, and each keeps its best, so that a machine whose
speed drifts over the minutes of the benchmark (a shared VM) times both alike. The line above
the table names the date, the CPU and the commit.
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import torch


def _oracle(gt, seed: int):
    from evtrack.tracking.pose_sources import OraclePoseSource

    return OraclePoseSource(gt.pose_at, std_translation=0.01, std_rotation=0.03, seed=seed)


def time_single(path: Path, repeats: int, config=None) -> tuple[float, int, float]:
    """(best seconds, events, duration s) of one tracker on a one-object sequence."""
    from evtrack import Sequence
    from evtrack.tracking.tracker import Tracker

    seq = Sequence.load(path)
    best = float("inf")
    for _ in range(repeats):
        tracker = Tracker.for_sequence(seq, config, _oracle(seq.ground_truth, 0))
        t0 = time.perf_counter()
        tracker.track(seq)
        best = min(best, time.perf_counter() - t0)
    duration = (int(seq.ground_truth.pose_t_us[-1]) - int(seq.ground_truth.pose_t_us[0])) * 1e-6
    return best, tracker.stats.events, duration


def time_multi(path: Path, repeats: int, config=None) -> tuple[float, int, int, float]:
    """(best seconds, events, objects, duration s) of a multi-object tracker."""
    from evtrack import Sequence
    from evtrack.tracking.multi import MultiTracker

    seq = Sequence.load(path)
    best = float("inf")
    for _ in range(repeats):
        sources = {o.name: _oracle(seq.object_ground_truth(k), k)
                   for k, o in enumerate(seq.objects)}
        multi = MultiTracker.for_sequence(seq, config, sources)
        t0 = time.perf_counter()
        multi.track(seq)
        best = min(best, time.perf_counter() - t0)
    gt = seq.ground_truth
    duration = (int(gt.pose_t_us[-1]) - int(gt.pose_t_us[0])) * 1e-6
    return best, multi.stats.events, len(seq.objects), duration


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--multi", type=Path, nargs="+", required=True, metavar="SEQ",
                        help="sequences with several objects")
    parser.add_argument("--single", type=Path, nargs="+", required=True, metavar="SEQ",
                        help="one-object sequences (the references)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="runs per sequence, the best is kept (default 1)")
    parser.add_argument("--config", type=Path, default=None, metavar="YAML",
                        help="tracker config of every run (default: the tracker's defaults)")
    args = parser.parse_args()
    from bench_tracker import cpu_model, short_commit

    from evtrack.tracking.config import TrackerConfig

    config = TrackerConfig.from_yaml(args.config) if args.config else None

    torch.set_num_threads(args.threads)
    print(f"# bench_multi_object.py, {datetime.date.today()}, {cpu_model()}, commit "
          f"{short_commit()}, "
          f"{args.threads} torch thread(s), oracle poses"
          + (f", config {args.config}" if args.config else ""))
    from evtrack import Sequence

    singles = [(path, Sequence.load(path).summary()["events"]) for path in args.single]
    print("| multi-object sequence | objects | events | time (s) | reference (one object) | "
          "its events | its time (s) | its time scaled (s) | ratio |")
    print("|:--|--:|--:|--:|:--|--:|--:|--:|--:|")
    for path in args.multi:
        events = Sequence.load(path).summary()["events"]
        ref, _ = min(singles, key=lambda s: abs(s[1] - events))
        best_multi = best_single = float("inf")
        for _ in range(args.repeats):  # in turn: a drifting machine times both alike
            s1, e1, _ = time_single(ref, 1, config)
            seconds, events, objects, _ = time_multi(path, 1, config)
            best_single, best_multi = min(best_single, s1), min(best_multi, seconds)
        scaled = best_single * events / max(e1, 1)
        print(f"| {path.parent.name}/{path.name} | {objects} | {events} | {best_multi:.2f} | "
              f"{ref.name} | {e1} | {best_single:.2f} | {scaled:.2f} | "
              f"{best_multi / scaled:.2f} |")


if __name__ == "__main__":
    main()
