"""``evtrack info FILE|FOLDER``: summarise an event file, a sequence folder or a pose network
(``.pt`` weights, ``.onnx`` export)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import torch

from evtrack.errors import ConfigError, EventFileError

__all__ = ["register", "run", "event_file_summary", "model_file_summary"]

MODEL_SUFFIXES = (".pt", ".ckpt", ".onnx")
"""Files summarised as pose networks, not as event files."""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "info",
        help="summarise an event file, a sequence folder or a pose network",
        description=(
            "Print what an event file holds (events, duration, event rate, sensor resolution, "
            "polarity balance, coordinate range), a sequence folder's summary (cameras, object, "
            "frames, ground truth) or a pose network's record (.pt weights, a Lightning .ckpt "
            "or an .onnx export: object, architecture, input size, cuboid, training, decoding). "
            "Event files are streamed, so files of many GB are fine."
        ),
    )
    parser.add_argument("path", type=Path, help="event file (.h5, .txt, .npz, .aedat4, .raw), "
                        "sequence folder (with meta.yaml) or pose network (.pt, .ckpt, .onnx)")
    parser.add_argument("--window-ms", type=float, default=100.0,
                        help="streaming window in ms while scanning the file (default: 100)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(func=run)


def event_file_summary(path: str | Path, window_us: int = 100_000) -> dict[str, Any]:
    """Scan an event file window by window and return its statistics.

    Returns:
        A dict with ``format``, ``events``, ``t_start_us``, ``t_end_us``, ``duration_s``,
        ``rate_ev_per_s``, ``sensor_size``, ``x_range``, ``y_range``, ``on_fraction``.
    """
    from evtrack.io import detect_format, iter_events, open_events

    reader = open_events(path)
    try:
        sensor = reader.sensor_size
    finally:
        reader.close()
    n = n_on = 0
    t0 = t1 = None
    xmin = ymin = None
    xmax = ymax = None
    for chunk in iter_events(path, window_us=window_us):
        if not len(chunk):
            continue
        n += len(chunk)
        n_on += int((chunk.p > 0).sum())
        t0 = chunk.t_start if t0 is None else t0
        t1 = chunk.t_end
        cx, cy = chunk.x.to(torch.int64), chunk.y.to(torch.int64)
        xmin = int(cx.min()) if xmin is None else min(xmin, int(cx.min()))
        ymin = int(cy.min()) if ymin is None else min(ymin, int(cy.min()))
        xmax = int(cx.max()) if xmax is None else max(xmax, int(cx.max()))
        ymax = int(cy.max()) if ymax is None else max(ymax, int(cy.max()))
    duration = (t1 - t0) * 1e-6 if n > 1 else 0.0
    return {
        "file": str(path),
        "format": detect_format(path),
        "events": n,
        "t_start_us": t0,
        "t_end_us": t1,
        "duration_s": duration,
        "rate_ev_per_s": n / duration if duration > 0 else None,
        "sensor_size": list(sensor) if sensor else None,
        "x_range": None if n == 0 else [xmin, xmax],
        "y_range": None if n == 0 else [ymin, ymax],
        "on_fraction": n_on / n if n else None,
    }


def model_file_summary(path: str | Path) -> dict[str, Any]:
    """The record of a pose network's file: ``.pt`` weights or a Lightning ``.ckpt`` (read with
    ``weights_only=True``) or an ``.onnx`` export (its embedded record, precision and opset).

    Raises:
        WeightsError: not a readable weights file or model, naming the file.
    """
    from evtrack.models.weights import WeightsError, load_weights_file, read_record

    path = Path(path)
    if path.suffix.lower() == ".onnx":
        import onnx

        record, precision = read_record(path)
        proto = onnx.load(str(path), load_external_data=False)
        opset = max((o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")),
                    default=None)
        kind = f"pose network, ONNX export ({precision.upper()}, opset {opset})"
        if record is None:
            raise WeightsError(path, "the model carries no weights record (not exported by "
                                     "'evtrack export pose')")
    else:
        record, state = load_weights_file(path)
        n = sum(int(v.numel()) for v in state.values() if hasattr(v, "numel"))
        kind = f"pose network weights (torch, {n:,} values)"
    c = record.cuboid.to_dict()
    cuboid = {"dimensions_m": [round(float(v), 6) for v in c["dimensions"]],
              "center_m": [round(float(v), 6) for v in c["center"]]}
    return {
        "file": str(path),
        "kind": kind,
        "object": record.object_name,
        "arch": record.arch + (f" {record.arch_kwargs}" if record.arch_kwargs else ""),
        "input_size": f"{record.input_size[1]}x{record.input_size[0]} (width x height)",
        "cuboid": cuboid,
        "created": record.created,
        "training_data": record.training_data or None,
        "training": record.training or None,
        "metrics": record.metrics or None,
        "decode": record.decode or "the library's defaults",
        "origin": record.origin or None,
        "licence": record.licence,
    }


def _format_value(key: str, value: Any) -> str:
    if value is None:
        return "-"
    if key == "rate_ev_per_s":
        return f"{value / 1e6:.3f} Mev/s"
    if key == "duration_s":
        return f"{value:.6f} s"
    if key == "on_fraction":
        return f"{value:.3f} ON / {1 - value:.3f} OFF"
    if key == "events":
        return f"{value:,}"
    return str(value)


def run(args: argparse.Namespace) -> int:
    path: Path = args.path
    if path.is_dir():
        from evtrack.sequence import Sequence

        summary = Sequence.load(path).summary()
    elif path.suffix.lower() in MODEL_SUFFIXES and path.is_file():
        summary = model_file_summary(path)
    else:
        if not path.exists():
            raise EventFileError(path, "no such file or folder")
        if not (math.isfinite(args.window_ms) and args.window_ms > 0):
            raise ConfigError(f"--window-ms must be a positive number, got {args.window_ms}")
        summary = event_file_summary(path, window_us=max(1, int(args.window_ms * 1000)))
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
        return 0
    width = max(len(k) for k in summary)
    for key, value in summary.items():
        print(f"{key:<{width}}  {_format_value(key, value)}")
    return 0
