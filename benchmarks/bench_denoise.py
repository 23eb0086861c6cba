"""The event denoiser (:mod:`evtrack.denoise`) on the real recordings of ``../shared``: what it
removes, how fast, and whether the flow measures the camera's rotation better or worse.

    python benchmarks/bench_denoise.py [--data DIR] [--repeats 3]

Files: the AEDAT4 (DVXplorer) and Prophesee EVT2/EVT3 samples of ``data/formats`` and the ECD
DAVIS240C cuts of ``data/real`` (``events.txt``, 240 x 180). No ground truth says which events
are noise: the share removed is what each filter takes, not how right it is.

Table 1, per file and background-activity setting (the three dv-processing filters at a 2 ms
window, and ``background_activity`` at the config's default, 5 ms): events in and out, the
share removed, and the throughput in M events/s of (a) ``copy``: the events into a
``dv.EventStore`` and back out as arrays with no filter (the cost of handing them to
dv-processing), (b) ``filter``: the dv filter alone on a store built beforehand, (c)
``denoiser``: the whole :class:`~evtrack.denoise.EventDenoiser` call (the checks, copy and
filter). Best of ``--repeats``, one thread.

Table 2, hot pixels alone (``denoise.hot_pixels``) with windows of 10, 50 and 100 ms (the
config's default): the pixels found hot, the events removed on them, and the denoiser's
throughput (100 ms). The windows are aligned on absolute time and a window's hot pixels are
known once it closes: a recording shorter than a window finds none.

Table 3, the ECD rotation samples: a hand-held camera turning at ``w`` (``motion.txt``, the
DAVIS IMU, rad/s) before a static scene, which then turns by ``-w`` relative to the camera.
The library's own flow and velocity filter at generic settings (``FlowConfig()`` with its 2 ms
windows; ``VelocityKFConfig()``; the camera with its lens distortion from ``calib.txt``), one
predict + update per flow window, every RoI at a constant depth of 0.7 m; the mean ``ω`` of the
second half of the sample (the filter starts from rest) against ``-w``: the cosine of the angle
and the magnitude ratio ``|mean ω| / |w|``, without the denoiser (``raw``) and with each
setting of table 1. Without the data folder the script says so and exits 0.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from evtrack.camera import PinholeCamera
from evtrack.denoise import DenoiseConfig, EventDenoiser, make_noise_filter, to_event_store
from evtrack.events import Events
from evtrack.io import read_events

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
ECD_SIZE = (240, 180)
DEPTH_M = 0.7  # the constant depth of the velocity filter's rows


def settings() -> dict[str, DenoiseConfig]:
    """The compared background-activity settings by label."""
    return {"background_activity 2 ms": DenoiseConfig(method="background_activity",
                                                      window_us=2000),
            "background_activity 5 ms": DenoiseConfig(method="background_activity",
                                                      window_us=5000),
            "knoise 2 ms": DenoiseConfig(method="knoise", window_us=2000),
            "fast_decay 2 ms": DenoiseConfig(method="fast_decay", window_us=2000)}


HOT_WINDOWS_US = (10_000, 50_000, 100_000)


def files(data: Path) -> list[tuple[str, Path, tuple[int, int] | None]]:
    """``(label, path, sensor size or None)`` of the recordings found under ``data``."""
    found = []
    formats = data / "formats"
    for label, rel in (("DVXplorer aedat4", "tonic_dvxplorer_aedat4/sample.aedat4"),
                       ("Prophesee EVT2", "expelliarmus_prophesee_raw/evt2_sample.raw"),
                       ("Prophesee EVT3", "expelliarmus_prophesee_raw/evt3_sample.raw")):
        if (formats / rel).is_file():
            found.append((label, formats / rel, None))
    for folder in sorted((data / "real").glob("ecd_*")):
        path = folder / "events.txt"
        if path.is_file():
            found.append((folder.name.removeprefix("ecd_").removesuffix("_sample"), path,
                          ECD_SIZE))
    return found


def _best(fn, repeats: int) -> tuple[float, object]:
    """The shortest of ``repeats`` calls of ``fn`` (s) and its last result."""
    best, out = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def throughput(ev: Events, cfg: DenoiseConfig, repeats: int) -> dict[str, float]:
    """M events/s of the copy, the filter alone and the whole denoiser on ``ev``."""
    arrays = (ev.t.numpy(), ev.x.numpy(), ev.y.numpy(), ev.p.numpy() > 0)

    def copy():
        out = to_event_store(*arrays).numpy()
        return Events(out["x"], out["y"], out["timestamp"],
                      np.where(out["polarity"].astype(bool), 1, -1), ev.sensor_size)

    n = len(ev)
    rate = {"copy": n / _best(copy, repeats)[0] * 1e-6}
    if cfg.method != "none":
        store = to_event_store(*arrays)

        def filtered():
            f = make_noise_filter(cfg, ev.sensor_size)
            f.accept(store)
            return f.generateEvents()

        rate["filter"] = n / _best(filtered, repeats)[0] * 1e-6
    rate["denoiser"] = n / _best(lambda: EventDenoiser(cfg, sensor_size=ev.sensor_size)(ev),
                                 repeats)[0] * 1e-6
    return rate


def read_motion(folder: Path) -> np.ndarray:
    """The camera's angular velocity ``w`` (3,) rad/s of a rotation sample."""
    return np.loadtxt(folder / "motion.txt", dtype=np.float64).reshape(3)


def read_camera(folder: Path) -> PinholeCamera:
    """The DAVIS240C of an ECD cut: ``calib.txt`` is ``fx fy cx cy k1 k2 p1 p2 k3``."""
    v = np.loadtxt(folder / "calib.txt", dtype=np.float64).reshape(-1)
    return PinholeCamera(*v[:4], *ECD_SIZE, dist=v[4:9])


def rotation(ev: Events, camera: PinholeCamera) -> np.ndarray:
    """The mean ``ω`` (3,) rad/s over the second half of ``ev`` of ``TripletFlow`` +
    ``VelocityKF`` at generic settings, one update per flow window at depth ``DEPTH_M``."""
    from evtrack.filters import VelocityKF
    from evtrack.flow import FlowConfig, TripletFlow

    flow = TripletFlow(FlowConfig(sensor_size=camera.size))
    res = flow(ev)
    kf = VelocityKF(camera)
    w_us = flow.config.window_us
    half = (ev.t_start + ev.t_end) / 2.0
    omegas = []
    for w in range(ev.t_start // w_us, ev.t_end // w_us + 1):
        rows = res.window == w
        if rows.any():
            uv = res.xy[rows].double()[None]
            depth = torch.full((1, uv.shape[1]), DEPTH_M, dtype=torch.float64)
            twist = kf(w_us * 1e-6, uv, depth, res.flow[rows].double()[None],
                       res.normal[rows][None])
        else:
            twist = kf.predict(w_us * 1e-6)
        if (w + 1) * w_us >= half:
            omegas.append(twist[0, 3:].numpy().copy())
    return np.mean(omegas, 0) if omegas else np.full(3, np.nan)


def _cos_ratio(omega: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    n, n_ref = float(np.linalg.norm(omega)), float(np.linalg.norm(ref))
    cos = float(omega @ ref) / (n * n_ref) if n > 0 else math.nan
    return cos, n / n_ref


def _print(rows: list[list[str]], header: list[str]) -> None:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    line = "  ".join(h.ljust(w) if i < 2 else h.rjust(w)
                     for i, (h, w) in enumerate(zip(header, widths, strict=True)))
    print(line)
    print("-" * len(line))
    for r in rows:
        print("  ".join(c.ljust(w) if i < 2 else c.rjust(w)
                        for i, (c, w) in enumerate(zip(r, widths, strict=True))), flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA,
                    help="the data folder holding formats/ and real/")
    ap.add_argument("--repeats", type=int, default=3, help="timings: best of this many")
    args = ap.parse_args(argv)
    found = files(args.data)
    if not found:
        print(f"no recordings under {args.data}: nothing to measure")
        return 0
    torch.set_num_threads(1)
    rows, hot_rows, flow_rows = [], [], []
    for label, path, size in found:
        ev = read_events(path, sensor_size=size) if size else read_events(path)
        span_ms = (ev.t_end - ev.t_start) * 1e-3
        folder = path.parent
        rotating = (folder / "motion.txt").is_file()
        if rotating:
            camera, w = read_camera(folder), read_motion(folder)
            flow_rows.append(_flow_row(label, "raw", ev, camera, w))
        for name, cfg in settings().items():
            out = EventDenoiser(cfg, sensor_size=ev.sensor_size)(ev)
            rate = throughput(ev, cfg, args.repeats)
            rows.append([label, name, str(len(ev)), f"{span_ms:.0f}", str(len(out)),
                         f"{1 - len(out) / len(ev):.1%}", f"{rate['copy']:.2f}",
                         f"{rate['filter']:.1f}", f"{rate['denoiser']:.2f}"])
            if rotating:
                flow_rows.append(_flow_row(label, name, out, camera, w))
        hot = []
        for window in HOT_WINDOWS_US:
            denoiser = EventDenoiser(DenoiseConfig(hot_pixels=True, hot_window_us=window),
                                     sensor_size=ev.sensor_size)
            denoiser(ev)
            hot += [str(denoiser.counts.hot_pixels_found), str(denoiser.counts.removed_hot)]
        rate = throughput(ev, DenoiseConfig(hot_pixels=True), args.repeats)
        hot_rows.append([label, f"{span_ms:.0f}", *hot, f"{rate['denoiser']:.1f}"])
    print(f"Background activity (M events/s: best of {args.repeats}, one thread)\n")
    _print(rows, ["file", "setting", "events", "ms", "out", "removed", "copy", "filter",
                  "denoiser"])
    print(f"\nHot pixels alone (x{DenoiseConfig().hot_factor:g} the "
          f"{DenoiseConfig().hot_percentile:g}th percentile of the active pixels' counts, "
          f">= {DenoiseConfig().hot_min_rate_hz:g} Hz): pixels found, events removed\n")
    _print(hot_rows, ["file", "ms", *(f"{k} {w // 1000} ms" for w in HOT_WINDOWS_US
                                      for k in ("hot px", "removed")), "denoiser M/s"])
    if flow_rows:
        print("\nECD rotation samples: TripletFlow + VelocityKF (generic settings, 0.7 m), mean "
              "ω of the second half against -w (IMU)\n")
        _print(flow_rows, ["sample", "events given", "events", "cos", "ratio", "|w| rad/s"])
    return 0


def _flow_row(label: str, name: str, ev: Events, camera: PinholeCamera, w: np.ndarray
              ) -> list[str]:
    cos, ratio = _cos_ratio(rotation(ev, camera), -w)
    return [label, name, str(len(ev)), f"{cos:+.3f}", f"{ratio:.3f}",
            f"{np.linalg.norm(w):.2f}"]


if __name__ == "__main__":
    sys.exit(main())
