"""Throughput of the event optical flow (events/s), batched vs the sequential reference.

Prints one table: for each chunk size, events per second of

* ``search``: the candidate search alone (burst filter + triplets), and
* ``flow``: the whole ``TripletFlow`` (search + RoI registration), fed one ``update()`` per
  chunk as a live stream would (``update`` works in pieces of the config's ``chunk_size``),

for each backend (``torch``: batched tensor code, with each ``--lookups`` way of finding an
event's predecessors in its chunk, ``passes`` or ``sorted``; ``compiled``: on CPU the numba
kernels of ``evtrack.flow.compiled`` and ``registration_compiled``, on CUDA the tensor search
with the Triton registration of ``evtrack.flow.registration_triton``, rows ``cuda
triton-reg``; each as :func:`evtrack.flow.backends.resolve` chooses it) on CPU with each of
``--threads`` thread counts (default 2) and on CUDA when available, next to the
sequential per-event reference of ``tests/flow/flow_reference.py`` run in the same process
on a prefix of the same events (it is far slower, so it sees fewer events). A calibration
line (int32 add throughput) helps compare runs on busy machines.

Targets (issue 4): >= 2 M events/s on 2 CPU cores, >= 50 M events/s on one GPU.

Two kinds of scene, because the cost is per *burst onset* (the events the triplet search and
the registration see) and the share of onsets differs:

* the translating texture (``--size``, ``--duration-ms``): a dense texture at a very high
  event rate; about 10 % of its events are onsets;
* a simulated sequence (``--sim OBJECT``, default ``006_mustard_bottle`` when
  ``../shared/data/ycb`` is present, else the procedural ``box``): 0.3 s of the ``faster``
  preset at 640x480, rendered at 4 kHz and cached, about 3 M ev/s with 25-30 % onsets; the
  case the target speaks of (a fast object at 640x480). ``--sim ''`` skips it;
  ``--sequence DIR`` adds recorded or simulated sequences.

Usage::

    python benchmarks/bench_flow_speed.py
    python benchmarks/bench_flow_speed.py --size 640x480 --duration-ms 20 --chunks 10000,1000000
    python benchmarks/bench_flow_speed.py --sim '' --sequence path/to/sequence
    python benchmarks/bench_flow_speed.py --config configs/flow_fast.yaml   # + that preset
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

# first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.runtime.openmp_wait)
import evtrack  # noqa: F401  # isort: skip
import torch

from evtrack.events import Events
from evtrack.flow import (
    CandidateSearch,
    FlowConfig,
    TripletFlow,
    numba_support,
    registration_triton,
)
from evtrack.flow.backends import resolve
from evtrack.flow.scenes import translating_texture
from evtrack.runtime.openmp_wait import wait_policy

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
    parser.add_argument("--cache", default="/tmp/evtrack_bench_flow_events.pt",
                        help="cache of the generated scene ('' to disable)")
    parser.add_argument("--no-cuda", action="store_true", help="skip CUDA (same as --devices cpu)")
    parser.add_argument("--devices", default="cpu,cuda",
                        help="comma-separated devices to measure (default cpu,cuda; CUDA only "
                             "when available); the sequential reference always runs")
    parser.add_argument("--sim", default=None,
                        help="object of the simulated scene (default: 006_mustard_bottle with "
                             "../shared, else box; '' to skip)")
    parser.add_argument("--sim-cache", type=Path, default=Path("/tmp/evtrack_bench_flow_sim"),
                        help="folder of the simulated scene")
    parser.add_argument("--sequence", type=Path, action="append", default=[],
                        help="a sequence folder to measure as well (repeatable)")
    parser.add_argument("--lookups", default="passes,sorted",
                        help="comma-separated FlowConfig.lookup values measured for the torch "
                             "backend, side by side (default passes,sorted)")
    parser.add_argument("--backends", default="torch,compiled",
                        help="comma-separated CPU backends to measure (default torch,compiled; "
                             "'compiled' alone skips the slow torch rows)")
    parser.add_argument("--config", type=Path, action="append", default=[],
                        help="a YAML flow config to measure besides the defaults (repeatable; "
                             "e.g. configs/flow_fast.yaml)")
    args = parser.parse_args(argv)
    thread_counts = [int(v) for v in args.threads.split(",")]
    torch.set_num_threads(thread_counts[0])
    w, h = (int(v) for v in args.size.lower().split("x"))
    cache = Path(args.cache) if args.cache else None
    scenes = [(f"translating texture {w}x{h}", _scene((w, h), args.duration_ms, cache))]
    sim_object = args.sim if args.sim is not None else _default_sim_object()
    if sim_object:
        scenes.append((f"simulated {sim_object}, faster, 640x480",
                       _sim_scene(sim_object, args.sim_cache)))
    for folder in args.sequence:
        from evtrack.sequence import Sequence

        scenes.append((f"sequence {folder}", Sequence.load(folder).events))
    print(f"torch {torch.__version__}, CPU threads {thread_counts}, "
          f"OMP_WAIT_POLICY {wait_policy()}")
    configs = [("defaults", FlowConfig())]
    configs += [(str(path), FlowConfig.from_yaml(path)) for path in args.config]
    for name, ev in scenes:
        for cfg_name, base in configs:
            _measure(name, ev, args, thread_counts, base, cfg_name)
    print("\ntarget: >= 2,000,000 ev/s on 2 CPU cores, >= 50,000,000 ev/s on one GPU "
          "(flow column)")
    return 0


def _default_sim_object() -> str:
    from evtrack.sim.objects import find_ycb_dir

    return "006_mustard_bottle" if find_ycb_dir() is not None else "box"


def _sim_scene(obj: str, folder: Path) -> Events:
    """0.3 s of the faster preset at 640x480, 4 kHz renders, cached in ``folder/obj``."""
    from evtrack.sequence import Sequence
    from evtrack.sim import SimConfig, resolve_object, simulate

    out = folder / obj
    if not (out / "events.h5").is_file():
        cfg = SimConfig.from_dict({"duration": 0.3, "seed": 27, "render": {"render_hz": 4000.0},
                                   "trajectory": {"preset": "faster"},
                                   "ground_truth": {"event_flow": False}})
        print(f"simulating {obj} (once; cached in {out}) ...", file=sys.stderr)
        simulate(resolve_object(obj), cfg, out, overwrite=True)
    return Sequence.load(out).events


def _measure(name: str, ev: Events, args, thread_counts: list[int], base: FlowConfig,
             cfg_name: str) -> None:
    """The table of one scene and one flow config."""
    w, h = ev.sensor_size
    rate_in = len(ev) / max(ev.duration_us, 1) * 1e6
    print(f"\nscene: {name}, {len(ev)} events over {ev.duration_us / 1000:.1f} ms "
          f"({rate_in / 1e6:.1f} M ev/s in the stream)")
    cfg = base.replace(sensor_size=(w, h))
    onsets = _count_onsets(cfg, ev)
    print(f"config {cfg_name}: radius {cfg.radius}, history {cfg.history}, refractory "
          f"{cfg.refractory_us} µs, tolerance {cfg.tolerance_rel:g}, span bound "
          f"{cfg.max_span_us or 'none'} µs, pieces of {cfg.chunk_size:,} events"
          f" -> {onsets / len(ev):.1%} of the events are burst onsets that are matched")

    sys.path.insert(0, str(ROOT / "tests" / "flow"))
    from flow_reference import reference_candidates

    torch.set_num_threads(thread_counts[0])
    sub = ev[: args.reference_events]
    t0 = time.perf_counter()
    reference_candidates(sub.x.tolist(), sub.y.tolist(), sub.t.tolist(), sub.p.tolist(),
                         (w, h), radius=cfg.radius, history=cfg.history,
                         refractory_us=cfg.refractory_us, tolerance_us=cfg.tolerance_us,
                         tolerance_permille=cfg.tolerance_permille, min_speed=cfg.min_speed,
                         max_speed=cfg.max_speed, max_span_us=cfg.max_span_us)
    ref_rate = len(sub) / (time.perf_counter() - t0)

    devices = {d.strip() for d in args.devices.split(",")}
    lookups = [v.strip() for v in args.lookups.split(",")]
    wanted = {v.strip() for v in args.backends.split(",")}
    runs = ([(torch.device("cpu"), n, b, lk) for n in thread_counts for b in _cpu_backends()
             if b in wanted for lk in (lookups if b == "torch" else ["-"])]
            if "cpu" in devices else [])
    if torch.cuda.is_available() and not args.no_cuda and "cuda" in devices:
        # the tensor registration and, where Triton is installed, the Triton kernel
        # (backend "compiled" on CUDA; the search is the tensor code in both)
        cuda_backends = ["torch"] + (["compiled"] if registration_triton.available("cuda")
                                     else [])
        runs += [(torch.device("cuda"), thread_counts[0], b, lk) for b in cuda_backends
                 for lk in lookups]
    print(f"{'device':<26}{'chunk':>10}{'search ev/s':>16}{'flow ev/s':>16}"
          f"{'x reference':>14}{'calib Gop/s':>13}")
    print(f"{'cpu/1 reference':<26}{'-':>10}{'(sequential)':>16}{ref_rate:>16,.0f}{1.0:>14.1f}")
    for dev, threads, backend, lookup in runs:
        torch.set_num_threads(threads)
        label = (f"cpu/{threads} {backend}" if dev.type == "cpu" else
                 f"cuda {'triton-reg' if backend == 'compiled' else 'torch'}")
        if backend == "torch" or dev.type == "cuda":
            label += f" {lookup}"
        sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
        evd = ev.to(dev)
        calib = _calibration(dev)
        for chunk in (int(c) for c in args.chunks.split(",")):
            # update() splits a chunk into pieces of the config's chunk_size, as for a user
            c = cfg.replace(device=str(dev), backend=backend,
                            **({"lookup": lookup} if lookup != "-" else {}))
            make_search = resolve(c, dev).search

            def search(c=c, evd=evd, dev=dev, make_search=make_search, chunk=chunk):
                s = make_search(c, dev)
                for i in range(0, len(evd), chunk):
                    s(evd.x[i:i + chunk], evd.y[i:i + chunk], evd.t[i:i + chunk],
                      evd.p[i:i + chunk])

            def flow(c=c, evd=evd, chunk=chunk):  # streaming: one update() per chunk
                f = TripletFlow(c)
                for i in range(0, len(evd), chunk):
                    f.update(evd[i:i + chunk])
                f.flush()

            r_search = _rate(search, len(ev), args.repeats, sync)
            r_flow = _rate(flow, len(ev), args.repeats, sync)
            print(f"{label:<26}{chunk:>10,}{r_search:>16,.0f}{r_flow:>16,.0f}"
                  f"{r_flow / ref_rate:>14.1f}{calib:>13.2f}")


def _cpu_backends() -> list[str]:
    return ["torch", "compiled"] if numba_support.available() else ["torch"]


def _count_onsets(cfg: FlowConfig, ev: Events) -> int:
    search = CandidateSearch(cfg.replace(refractory_us=cfg.refractory_us))
    pix = ev.x.to(torch.int64), ev.y.to(torch.int64), ev.t, ev.p
    return int(search._onsets(*pix).sum())


if __name__ == "__main__":
    raise SystemExit(main())
