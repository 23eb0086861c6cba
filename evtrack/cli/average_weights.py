"""``evtrack average-weights A B [...] --out C.pt``: one weights file, the mean of several."""

from __future__ import annotations

import argparse
from pathlib import Path

from evtrack.cli._parsers import command_parser

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = command_parser(
        subparsers, "average-weights",
        "average several weights files of one network (a model soup)",
        "Write the mean of two or more pose-network weights files (or 'evtrack train' "
        "checkpoints) of one architecture and object: e.g. a run and its continuation, or "
        "the last checkpoints of runs from one start. Weights and batch-norm statistics "
        "are averaged; the record (and the model card written beside the file) names the "
        "files and drops their metrics (measure the "
        "result, e.g. with benchmarks/bench_pose_accuracy.py). For an average over the "
        "steps of one run, train with optim.ema_decay instead.",
        "example:\n  evtrack average-weights runs/pose/a/x.pt runs/pose/b/x.pt "
        "--out runs/pose/soup/x.pt")
    parser.add_argument("weights", type=Path, nargs="+",
                        help="weights files (.pt) or checkpoints (.ckpt), two or more")
    parser.add_argument("--out", type=Path, required=True, help="the weights file to write")
    parser.add_argument("--factors", type=float, nargs="+", default=None,
                        help="one weight per file (normalised to sum 1; default: equal)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from evtrack.models import load_weights_file, write_model_card
    from evtrack.models.averaging import average_weights

    path = average_weights(args.weights, args.out, args.factors)
    card = write_model_card(path.with_suffix(".md"), load_weights_file(path)[0])
    print(f"wrote the mean of {len(args.weights)} weights files to {path} (model card {card})")
    return 0
