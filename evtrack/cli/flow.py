"""``evtrack flow IN --out DIR``: event optical flow of an event file, with pictures."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch
import yaml

from evtrack.errors import ConfigError
from evtrack.utils import output_folder

__all__ = ["register", "run"]

FORMATS = ("csv", "h5", "npz")
OUTPUT_NAMES = (*(f"flow.{f}" for f in FORMATS), "flow.png", "flow.mp4", "flow_config.yaml")
"""What ``evtrack flow`` writes into its folder."""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "flow",
        help="optical flow of an event file (triplet matching, RoI registration)",
        description=(
            "Estimate event optical flow (px/s) per region of interest and time window by "
            "triplet matching (method paper, Sec. III-A) and write it with a picture: a "
            "colour-wheel image of the RoI flows and arrows over the accumulated events "
            "(orange arrows: normal flow only, aperture). The file is streamed."
        ),
    )
    parser.add_argument("input", type=Path, help="event file (.h5, .txt, .npz, .aedat4, .raw)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--config", type=Path, help="YAML flow config (see configs/flow.yaml)")
    parser.add_argument("--roi", type=int, help="RoI size in px (overrides the config)")
    parser.add_argument("--window-ms", type=float, help="registration window in ms (overrides)")
    parser.add_argument("--device", help="torch device, e.g. cpu or cuda (overrides)")
    parser.add_argument("--format", choices=FORMATS, default="csv",
                        help="flow file format (default: csv)")
    parser.add_argument("--event-flow", action="store_true",
                        help="also store one flow per event (h5/npz formats)")
    parser.add_argument("--video", action="store_true", help="also write flow.mp4")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier run's outputs in the folder (flow.csv, "
                             "flow.h5, flow.npz, flow.png, flow.mp4, flow_config.yaml; other "
                             "files there stay)")
    parser.add_argument("--frame-ms", type=float, default=33.0,
                        help="time span of one picture / video frame in ms (default: 33)")
    parser.add_argument("--fps", type=float, default=30.0, help="video frame rate (default 30)")
    parser.add_argument("--read-ms", type=float, default=50.0,
                        help="events are read in pieces of this many ms (default: 50)")
    parser.set_defaults(func=run)


def _config(args: argparse.Namespace):
    from evtrack.flow import FlowConfig

    cfg = FlowConfig.from_yaml(args.config) if args.config else FlowConfig()
    changes = {}
    if args.roi is not None:
        changes["roi_size"] = args.roi
    if args.window_ms is not None:
        changes["window_us"] = int(round(args.window_ms * 1000))
    if args.device is not None:
        changes["device"] = args.device
    return cfg.replace(**changes) if changes else cfg


class _Frames:
    """Collects events and RoI flows per frame span and renders finished frames."""

    def __init__(self, frame_us: int, flow, video, max_speed: float) -> None:
        self.frame_us = frame_us
        self.flow = flow
        self.video = video
        self.max_speed = max_speed
        self.events: dict[int, list] = {}
        self.rows: dict[int, list] = {}
        self.best: tuple[int, np.ndarray | None] = (-1, None)

    def add_events(self, ev) -> None:
        idx = torch.div(ev.t, self.frame_us, rounding_mode="floor")
        for k in torch.unique(idx).tolist():
            self.events.setdefault(k, []).append(ev[idx == k])

    def add_rows(self, res, upto_us: int | None) -> None:
        if len(res):
            idx = torch.div(res.t.cpu(), self.frame_us, rounding_mode="floor")
            for k in torch.unique(idx).tolist():
                m = idx == k
                self.rows.setdefault(k, []).append((res.xy.cpu()[m], res.flow.cpu()[m],
                                                    res.normal.cpu()[m]))
        done = [k for k in sorted(set(self.events) | set(self.rows))
                if upto_us is None or (k + 1) * self.frame_us <= upto_us]
        for k in done:
            self._render(k)

    def _render(self, k: int) -> None:
        from evtrack.events import concatenate
        from evtrack.flow.visualize import render_flow

        evs = self.events.pop(k, [])
        rows = self.rows.pop(k, [])
        xy = torch.cat([r[0] for r in rows]) if rows else torch.zeros(0, 2)
        fl = torch.cat([r[1] for r in rows]) if rows else torch.zeros(0, 2)
        nm = torch.cat([r[2] for r in rows]) if rows else torch.zeros(0, dtype=torch.bool)
        need_png = xy.shape[0] > self.best[0]
        if self.video is None and not need_png:
            return
        ev = concatenate(evs) if evs else None
        if ev is None:
            from evtrack.events import Events

            ev = Events.empty(self.flow.config.sensor_size)
        img = render_flow(ev, xy, fl, nm, self.flow.config.sensor_size,
                          self.flow.config.roi_size, max_speed=self.max_speed)
        if self.video is not None:
            self.video.write(img)
        if need_png:
            self.best = (xy.shape[0], img)


def run(args: argparse.Namespace) -> int:
    from evtrack.flow import TripletFlow
    from evtrack.io import open_events

    cfg = _config(args)
    if args.event_flow and args.format == "csv":
        raise ConfigError("--event-flow needs --format h5 or npz (one row per event)")
    if args.frame_ms <= 0 or args.read_ms <= 0:
        raise ConfigError("--frame-ms and --read-ms must be positive")
    reader = open_events(args.input)
    try:
        sensor = reader.sensor_size
    finally:
        reader.close()
    if cfg.sensor_size is None:
        if sensor is None:
            raise ConfigError(f"{args.input}: the file does not say its sensor size; set "
                              "sensor_size in the flow config")
        cfg = cfg.replace(sensor_size=tuple(sensor))
    flow = TripletFlow(cfg, return_event_flow=args.event_flow)
    frame_us = max(cfg.window_us, int(round(args.frame_ms * 1000 / cfg.window_us))
                   * cfg.window_us)
    if not (math.isfinite(args.frame_ms) and math.isfinite(args.read_ms)) or args.fps <= 0:
        raise ConfigError("--frame-ms and --read-ms must be finite and --fps positive")
    with output_folder(args.out, OUTPUT_NAMES, args.overwrite,  # a failed run leaves nothing
                       inputs={"input": args.input, "--config": args.config}):
        return _flow_into_folder(args, cfg, flow, frame_us)


def _flow_into_folder(args: argparse.Namespace, cfg, flow, frame_us: int) -> int:
    """The flow of ``args.input`` into the folder ``args.out`` (made): files, picture, video."""
    from evtrack.flow import FlowResult
    from evtrack.flow.visualize import VideoWriter, save_png
    from evtrack.io import iter_events
    from evtrack.utils import atomic_write_text

    video = VideoWriter(args.out / "flow.mp4", args.fps) if args.video else None
    frames = _Frames(frame_us, flow, video, max_speed=cfg.max_speed / 10)
    parts = []
    n_events = 0
    try:
        for piece in iter_events(args.input, window_us=int(args.read_ms * 1000)):
            if not len(piece):
                continue
            n_events += len(piece)
            piece = _with_size(piece, cfg.sensor_size)
            res = flow.update(piece)
            parts.append(res.to("cpu"))
            frames.add_events(piece)
            # frames are complete once the flow windows up to their end are reported
            upto = (int(res.window.max()) + 1) * cfg.window_us if len(res) else -1
            frames.add_rows(res, upto)
        tail = flow.flush().to("cpu")
        parts.append(tail)
        frames.add_rows(tail, None)
        result = FlowResult.cat(parts)
        result.save(args.out / f"flow.{args.format}")
        if frames.best[1] is not None:
            save_png(args.out / "flow.png", frames.best[1])
        atomic_write_text(args.out / "flow_config.yaml",
                          yaml.safe_dump(cfg.to_dict(), sort_keys=False))
        if video is not None:
            video.close()
            video = None
    finally:
        if video is not None:
            video.abort()
    normal = int(result.normal.sum())
    print(f"{args.input}: {n_events} events -> {len(result)} RoI flows "
          f"({normal} normal-flow only) in {args.out}", file=sys.stdout)
    return 0


def _with_size(events, sensor_size):
    """The same events, labelled with the flow's sensor size when the file gave none."""
    if events.sensor_size is not None:
        return events
    from evtrack.events import Events

    return Events(events.x, events.y, events.t, events.p, tuple(sensor_size))
