"""``evtrack set-decode W.pt KEY=VALUE [...]``: store a network's chosen decoding with it."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import yaml

from evtrack.cli._parsers import command_parser
from evtrack.errors import ConfigError

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = command_parser(
        subparsers, "set-decode",
        "store the decoding settings chosen for a network in its weights file",
        "Set the record's decoding (WeightsRecord.decode: DecodeConfig fields that differ "
        "from the library's defaults) of a pose-network weights file. Estimators built from "
        "the file, and from its ONNX export, then decode with them unless given a decode of "
        "their own; 'evtrack evaluate' and 'evtrack track' use them. Choose them on held-out "
        "renders, e.g. 'python benchmarks/bench_pose_accuracy.py --weights W.pt "
        "--crop-blend 45', not on the sequences you report. The state dict is copied as it "
        "is; the file is replaced atomically (or written to --out).",
        "examples:\n"
        "  evtrack set-decode runs/pose/x/x.pt crop_blend_max_deg=45\n"
        "  evtrack set-decode runs/pose/x/x.pt search_below=0.2 --out x_decoded.pt\n"
        "  evtrack set-decode runs/pose/x/x.pt --clear        # back to the defaults")
    parser.add_argument("weights", type=Path, help="weights file (.pt)")
    parser.add_argument("settings", nargs="*", metavar="KEY=VALUE",
                        help="DecodeConfig fields (values read as YAML scalars)")
    parser.add_argument("--clear", action="store_true",
                        help="drop the record's settings first (then KEY=VALUE, if any)")
    parser.add_argument("--out", type=Path, default=None,
                        help="write here instead of replacing the file")
    parser.set_defaults(func=run)


def parse_settings(items: list[str]) -> dict[str, Any]:
    """``["key=value", ...]`` -> ``{key: value}``, each value a YAML scalar (never evaluated)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"decode setting {item!r}: expected KEY=VALUE, e.g. "
                              "crop_blend_max_deg=45")
        value = yaml.safe_load(text)
        if isinstance(value, dict | list):
            raise ConfigError(f"decode setting {key!r}: expected a single value, got {text!r}")
        out[key.strip()] = value
    return out


def run(args: argparse.Namespace) -> int:
    from evtrack.models import load_weights_file, set_record_decode

    if not args.settings and not args.clear:
        record, _ = load_weights_file(args.weights)
        print(f"{args.weights}: decode {record.decode or '{} (the library defaults)'}")
        return 0
    record, _ = load_weights_file(args.weights)
    decode = {} if args.clear else dict(record.decode)
    decode.update(parse_settings(args.settings))
    path = set_record_decode(args.weights, decode, args.out)
    print(f"wrote {path}: decode {decode or '{} (the library defaults)'}; state dict unchanged "
          "(update the model card's 'Decoding' line if it has one)")
    return 0
