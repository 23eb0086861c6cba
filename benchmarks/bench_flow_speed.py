"""Throughput of the event optical flow (events/s), batched vs the sequential reference.

Prints one table: for each chunk size, events per second of

* ``search``: the batched candidate search alone (burst filter + triplets), and
* ``flow``: the whole ``TripletFlow`` (search + RoI registration),

on CPU with each of ``--threads`` thread counts (default 2) and on CUDA when available, next to the
sequential per-event reference of ``tests/flow/flow_reference.py`` run in the same process
on a prefix of the same events (it is far slower, so it sees fewer events). A calibration
line (int32 add throughput) helps compare runs on busy machines.

Targets (issue 4): >= 2 M events/s on 2 CPU cores, >= 50 M events/s on one GPU.

Usage::

    python benchmarks/bench_flow_speed.py                     # 346x260 textured scene
    python benchmarks/bench_flow_speed.py --size 640x480 --duration-ms 20 --chunks 10000,1000000
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from evtrack.events import Events
from evtrack.flow import CandidateSearch, FlowConfig, TripletFlow
from evtrack.flow.scenes import translating_texture

ROOT = Path(__file__).resolve().parents[1]


def _scene(size: tuple[int, int], duration_ms: float, cache: Path | None) -> Events:
    if cache is not None and cache.is_file():
        d = torch.load(cache, weights_only=True)
        return Events(d["x"], d["y"], d["t"], d["p"], tuple(d["size"]))
    ev, _ = translating_texture(size, velocity=(1200.0, -500.0),
                                duration_us=int(duration_ms * 1000), seed=11)
    if cache is not None:
        torch.save({"x": ev.x, "y": ev.y, "t": ev.t, "p": ev.p, "size": list(size)}, cache)
    return ev


def _rate(fn, n_events: int, repeats: int, sync) -> float:
    best = float("inf")
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        best = min(best, time.perf_counter() - t0)
    return n_events / best


def _calibration(device: torch.device) -> float:
    a = torch.ones(20_000_000, dtype=torch.int32, device=device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    return _rate(lambda: a + 1, a.numel(), 5, sync) / 1e9


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="346x260", help="sensor WxH (default 346x260)")
    parser.add_argument("--duration-ms", type=float, default=40.0)
    parser.add_argument("--chunks", default="10000,100000,1000000",
                        help="comma-separated chunk sizes")
    parser.add_argument("--threads", default="2",
                        help="comma-separated CPU thread counts to measure (default 2)")
    parser.add_argument("--reference-events", type=int, default=20_000,
                        help="events given to the sequential reference")
    parser.add_argument("--repeats", type=int, default=2, help="best of this many runs")
    parser.add_argument("--cache", type=Path, default=Path("/tmp/evtrack_bench_flow_events.pt"),
                        help="cache of the generated scene ('' to disable)")
    parser.add_argument("--no-cuda", action="store_true")
    args = parser.parse_args(argv)
    thread_counts = [int(v) for v in args.threads.split(",")]
    torch.set_num_threads(thread_counts[0])
    w, h = (int(v) for v in args.size.lower().split("x"))
    cache = args.cache if str(args.cache) else None
    ev = _scene((w, h), args.duration_ms, cache)
    rate_in = len(ev) / max(ev.duration_us, 1) * 1e6
    print(f"scene: translating texture {w}x{h}, {len(ev)} events over {ev.duration_us / 1000:.1f}"
          f" ms ({rate_in / 1e6:.1f} M ev/s in the stream); torch {torch.__version__}, "
          f"CPU threads {thread_counts}")
    cfg = FlowConfig(sensor_size=(w, h))
    onsets = _count_onsets(cfg, ev)
    print(f"config: radius {cfg.radius}, history {cfg.history}, refractory {cfg.refractory_us} µs"
          f" -> {onsets / len(ev):.1%} of the events are burst onsets that are matched")

    sys.path.insert(0, str(ROOT / "tests" / "flow"))
    from flow_reference import reference_candidates

    sub = ev[: args.reference_events]
    t0 = time.perf_counter()
    reference_candidates(sub.x.tolist(), sub.y.tolist(), sub.t.tolist(), sub.p.tolist(),
                         (w, h), radius=cfg.radius, history=cfg.history,
                         refractory_us=cfg.refractory_us, tolerance_us=cfg.tolerance_us,
                         tolerance_permille=cfg.tolerance_permille, min_speed=cfg.min_speed,
                         max_speed=cfg.max_speed)
    ref_rate = len(sub) / (time.perf_counter() - t0)

    runs = [(torch.device("cpu"), n) for n in thread_counts]
    if torch.cuda.is_available() and not args.no_cuda:
        runs.append((torch.device("cuda"), thread_counts[0]))
    print()
    print(f"{'device':<9}{'chunk':>10}{'search ev/s':>16}{'flow ev/s':>16}"
          f"{'x reference':>14}{'calib Gop/s':>13}")
    print(f"{'cpu/1':<9}{'-':>10}{'(reference)':>16}{ref_rate:>16,.0f}{1.0:>14.1f}{'':>13}")
    for dev, threads in runs:
        torch.set_num_threads(threads)
        name = f"cpu/{threads}" if dev.type == "cpu" else "cuda"
        sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
        evd = ev.to(dev)
        calib = _calibration(dev)
        for chunk in (int(c) for c in args.chunks.split(",")):
            c = cfg.replace(chunk_size=chunk, device=str(dev))

            def search(c=c, evd=evd, dev=dev):
                CandidateSearch(c, dev)(evd.x, evd.y, evd.t, evd.p)

            def flow(c=c, evd=evd):
                TripletFlow(c)(evd)

            r_search = _rate(search, len(ev), args.repeats, sync)
            r_flow = _rate(flow, len(ev), args.repeats, sync)
            print(f"{name:<9}{chunk:>10,}{r_search:>16,.0f}{r_flow:>16,.0f}"
                  f"{r_flow / ref_rate:>14.1f}{calib:>13.2f}")
    print("\ntarget: >= 2,000,000 ev/s on 2 CPU cores, >= 50,000,000 ev/s on one GPU "
          "(flow column)")
    return 0


def _count_onsets(cfg: FlowConfig, ev: Events) -> int:
    search = CandidateSearch(cfg.replace(refractory_us=cfg.refractory_us))
    pix = ev.x.to(torch.int64), ev.y.to(torch.int64), ev.t, ev.p
    return int(search._onsets(*pix).sum())


if __name__ == "__main__":
    raise SystemExit(main())
