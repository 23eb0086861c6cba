"""How much of the true motion the tracker's twist carries, on simulated sequences.

For each sequence and config (the defaults first, then each ``--variant``, side by side in one
process), the tracker runs with the ground-truth poses as its pose source (``OraclePoseSource``,
no noise by default: what remains is the event pipeline's own error), and its twists are
compared with the simulator's (``evtrack.eval.twist_metrics``): the gain of the angular and
linear parts, of the object centre's velocity (image plane, depth) and of the rotation along
and across the line of sight, the twist errors, and the pose errors that follow.

A gain below 1 means the twist carries only that share of the true motion. The pose filter
integrates the twist between two poses, so the pose lags the object by the missing share over
each pose period, whatever pose source corrects it.

Usage::

    python benchmarks/bench_twist_accuracy.py tuning/*_faster_* \\
        --variant velocity_kf.laplace_scale_min=30 --duration 1

``--variant`` takes ``section.field=value`` overrides of the tracker config, several joined by
commas; ``--oracle-noise T R`` adds pose noise (metres, radians) as ``evtrack evaluate
--oracle`` does.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from evtrack import Sequence, configs
from evtrack.eval.metrics import tracking_errors
from evtrack.eval.twist_metrics import twist_agreement
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import OraclePoseSource
from evtrack.tracking.tracker import Tracker

COLUMNS = ("gain ω", "gain v_o", "gain v_c xy", "gain v_c z", "ω along", "ω across",
           "rmse ω rad/s", "rmse v_c m/s", "pos cm", "rot deg", "time s")


def run(path: Path, overrides: tuple[str, ...], noise: tuple[float, float], seed: int,
        duration_s: float | None) -> list[str]:
    """One sequence with one config: the table row's cells."""
    sequence = Sequence.load(path)
    gt = sequence.ground_truth
    config = TrackerConfig.from_dict(configs.apply_overrides({}, overrides), "--variant")
    source = OraclePoseSource(gt.pose_at, std_translation=noise[0], std_rotation=noise[1],
                              seed=seed)
    tracker = Tracker.for_sequence(sequence, config, source)
    started = time.perf_counter()
    trajectory = tracker.track(sequence)
    elapsed = time.perf_counter() - started
    if duration_s is not None:
        trajectory = trajectory[trajectory.t_us <= trajectory.t_us[0] + int(duration_s * 1e6)]
    tracked = trajectory[trajectory.tracked]
    truth_twists = gt.twist_at(tracked.t_us)
    centres = gt.pose_at(tracked.t_us)[:, :3, 3]
    agreement = twist_agreement(tracked.twists, truth_twists, centres)
    errors = tracking_errors(trajectory, gt)
    return [f"{agreement.gain_angular:.3f}", f"{agreement.gain_linear:.3f}",
            f"{agreement.gain_centre_image:.3f}", f"{agreement.gain_centre_depth:.3f}",
            f"{agreement.gain_along_sight:.3f}", f"{agreement.gain_across_sight:.3f}",
            f"{agreement.rmse_angular_rad_s:.2f}", f"{agreement.rmse_centre_m_s:.3f}",
            f"{errors.position_rmse_cm:.2f}", f"{errors.rotation_rmse_deg:.2f}",
            f"{elapsed:.1f}"]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description="The tracker's twist against the simulator's, with ground-truth poses as "
                    "the pose source: how much of the motion it carries (gains) and the pose "
                    "error that follows, per sequence and config.")
    parser.add_argument("sequences", nargs="+", type=Path,
                        help="simulated sequence folders (groundtruth.h5 with twists)")
    parser.add_argument("--variant", action="append", default=[],
                        help="tracker config overrides 'section.field=value[,...]', compared "
                             "with the defaults (repeatable)")
    parser.add_argument("--oracle-noise", nargs=2, type=float, default=(0.0, 0.0),
                        metavar=("T_M", "R_RAD"),
                        help="pose noise of the oracle: translation (m), rotation (rad); "
                             "default 0 0")
    parser.add_argument("--seed", type=int, default=0, help="the oracle noise's seed")
    parser.add_argument("--duration", type=float, default=None,
                        help="compare the first DURATION seconds only (the run sees it all)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    variants = [("defaults", ())] + [
        (text, tuple(part.strip() for part in text.split(",") if part.strip()))
        for text in args.variant]
    print("| sequence | config | " + " | ".join(COLUMNS) + " |")
    print("|:--|:--|" + "--:|" * len(COLUMNS))
    for path in args.sequences:
        for name, overrides in variants:
            cells = run(path, overrides, tuple(args.oracle_noise), args.seed, args.duration)
            print(f"| {path.name} | {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
