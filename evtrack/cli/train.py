"""``evtrack train --config configs/pose_<object>.yaml``: train a pose network with Lightning."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train",
        help="train a pose network (belief maps + affinity fields) on synthetic images",
        description=(
            "Train a DOPE-style pose network from a YAML config (see configs/pose_*.yaml). "
            "Writes checkpoints, CSV logs, the resolved config, and at the end the best "
            "network as a weights file with its model card under OUTPUT_DIR/RUN_NAME/. "
            "Multi-GPU and multi-node training: set trainer.devices / trainer.num_nodes / "
            "trainer.strategy in the config (passed to lightning.Trainer)."
        ),
    )
    parser.add_argument("--config", type=Path, required=True, help="YAML training config")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
        help="override a config field (value parsed as YAML); repeatable, e.g. "
             "--set trainer.max_epochs=5 --set data.batch_size=8",
    )
    parser.add_argument(
        "--resume", default=None, metavar="auto|CHECKPOINT",
        help="continue a run: 'auto' picks OUTPUT_DIR/RUN_NAME/checkpoints/last.ckpt if it "
             "exists, or give a checkpoint path",
    )
    parser.add_argument("--print-config", action="store_true",
                        help="print the resolved config (defaults filled in) and exit")
    parser.add_argument("--fast-dev-run", action="store_true",
                        help="run one training and one validation batch, write no weights")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or model summary")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import yaml

    from evtrack.train.config import TrainConfig

    config = TrainConfig.from_yaml(args.config, args.overrides)
    if args.print_config:
        print(yaml.safe_dump(config.to_dict(), sort_keys=False), end="")
        return 0
    from evtrack.train.fit import run_training

    result = run_training(config, resume=args.resume, fast_dev_run=args.fast_dev_run,
                          verbose=not args.quiet)
    print(f"run folder: {result.run_dir}")
    if result.weights is not None:
        print(f"weights:    {result.weights}")
        print(f"model card: {result.card}")
    for key in sorted(k for k in result.metrics if k.startswith("val/")):
        print(f"{key}: {result.metrics[key]:.6g}")
    print(f"wall time:  {result.wall_time_s:.1f} s")
    return 0
