"""``evtrack export TARGET ...``: export trained models for deployment.

Targets are sub-commands, each registered by one function in :data:`TARGETS`; today:

* ``evtrack export pose --weights W --out model.onnx [--fp16] [--opset N]``: a pose network
  (weights file or ``evtrack train`` checkpoint) to ONNX with dynamic batch and image size.

To add a target, write ``_register_<name>(subparsers)`` that adds a parser with
``set_defaults(export_func=...)`` and append it to :data:`TARGETS`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

__all__ = ["register", "run", "TARGETS"]


def _export_pose(args: argparse.Namespace) -> int:
    from evtrack.models import count_parameters, export_onnx, load_model

    net, record = load_model(args.weights, object_name=args.object)
    path = export_onnx(net, args.out, record=record, fp16=args.fp16, opset=args.opset)
    size_mb = Path(path).stat().st_size / 1e6
    print(f"exported {record.arch} for object {record.object_name!r} "
          f"({count_parameters(net):,} parameters, {'FP16' if args.fp16 else 'FP32'}) "
          f"to {path} ({size_mb:.2f} MB)")
    return 0


def _register_pose(subparsers: argparse._SubParsersAction) -> None:
    from evtrack.models.onnx_export import DEFAULT_OPSET

    p = subparsers.add_parser(
        "pose",
        help="a pose network to ONNX",
        description=(
            "Export a pose network to ONNX: input 'image' float32 (B,3,H,W) normalised as the "
            "weights record says, outputs 'belief' (B,9,H/8,W/8) and 'affinity' "
            "(B,16,H/8,W/8); batch, H and W are dynamic (H, W multiples of 8). The weights "
            "record is embedded, so evtrack.models.OnnxPoseEstimator needs only the file."
        ),
    )
    p.add_argument("--weights", type=Path, required=True,
                   help="weights file (.pt) or 'evtrack train' checkpoint (.ckpt)")
    p.add_argument("--out", type=Path, required=True, help="output .onnx file")
    p.add_argument("--fp16", action="store_true",
                   help="half-precision weights and compute (inputs/outputs stay float32)")
    p.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                   help=f"ONNX opset (default: {DEFAULT_OPSET})")
    p.add_argument("--object", default=None,
                   help="refuse weights trained for another object than this one")
    p.set_defaults(export_func=_export_pose)


TARGETS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (_register_pose,)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export",
        help="export a trained model (e.g. the pose network to ONNX)",
        description="Export a trained model for deployment. Run 'evtrack export TARGET --help'.",
    )
    targets = parser.add_subparsers(dest="target", metavar="TARGET")
    for add in TARGETS:
        add(targets)
    parser.set_defaults(func=run, export_parser=parser)


def run(args: argparse.Namespace) -> int:
    func = getattr(args, "export_func", None)
    if func is None:
        args.export_parser.print_help()
        return 2
    return int(func(args) or 0)
