"""The tracker's CPU-side speed-ups, each against the code without it, side by side.

    python benchmarks/bench_tracker_cpu.py --sequence DIR [DIR ...] [--repeats 2]
                                           [--variants reference blas strips mask groups kf
                                                       depth eq3 sample budget runs long]

Variants, cumulative (each adds one change to the one before):

* ``reference``: numpy's BLAS on its own threads (``blas_threads: 0``), the flow's candidate
  search in one loop (no strips), the event mask by the half-plane point test
  (:func:`evtrack.tracking.silhouette.points_in_polygon`, a (N, edges) product);
* ``blas``: numpy's BLAS on one thread while tracking (:mod:`evtrack.runtime.blas_threads`):
OpenBLAS's
  idle workers no longer spin after the mask's product;
* ``strips``: the search split into horizontal strips of the sensor, one per thread
  (:class:`evtrack.flow.compiled.CompiledSearch`);
* ``mask``: the event mask by row spans (:func:`evtrack.tracking.silhouette.pixels_in_polygon`);
* ``groups``: one flow call per 10 velocity steps instead of 5 (``flow_batch_steps``);
* ``kf``: the filters' single-track steps compiled with numba
  (:mod:`evtrack.filters.fast_compiled`: the velocity update, the pose predict) instead of
  NumPy;
* ``depth``: the RoI depth lookup compiled (``evtrack.tracking.depth_sources.COMPILED``);
* ``eq3``: the tracker's Eq. 3 caps, 16 hypotheses from at most 32 events per RoI window
  (the flow's generic 48 from 64 before);
* ``sample``: the flow searches a hash sample of about 64 events of each RoI window
  (``load.search_per_roi_window``; every event still enters the search's history);
* ``budget``: of those, at most 2500 events per velocity step are searched, by whole RoIs
  (``load.max_searched_per_step``), the tracker's default;
* ``runs``: the velocity steps between two events of the stream (a frame, a pose due) in
  the filters' compiled runs (``Tracker.step_runs``: ``VelocityKF.forward_run``,
  ``PoseTimeline.step_run``), a few calls for ~10 steps instead of a few dozen per step, and
  the steps a late first pose measures again a step group per velocity run;
* ``long``: one flow call per 40 velocity steps instead of 10 (``flow_batch_steps``, the
  default): each call's fixed cost (Python, small kernels, thread wake-ups) is paid a quarter
  as often. All twelve changes, the tracker as it ships.

The variants before ``kf`` run the NumPy steps (``set_default_backend("numpy")``). Not a variant:
the tracker's per-step bookkeeping (the pose as a matrix, the recorded outputs, one pivot per
step group, the view test on the bounding box, the timeline's shared snapshot copies, one
pass of checks per velocity predict + update) was made cheaper along the way and is in every
variant, as are the later small-call savings of the flow (registration kernels without hidden
parallel loops, compiled group keys and counts), the NumPy gather of the event mask and the
compiled row spans, and the pose source in ``track``'s worker thread (``pose_async``).

All but ``groups``, ``eq3``, ``sample``, ``budget`` and ``long`` give the same trajectory as the
variant before up to float rounding (the strips and the runs bit for bit; the BLAS thread count
and the mask's arithmetic can move an event on the mask's edge); ``groups`` and ``long`` mask 10
and 40 steps of events with the hull of the silhouettes predicted at their first step and at
their last step's end (its errors on the benchmark sets: see
``TrackerConfig.flow_batch_steps``); ``eq3`` solves Eq. 3 over fewer hypotheses (its errors: see
``evtrack.tracking.config``), ``sample`` the data term of fewer events in the crowded windows
(see ``evtrack.tracking.tracker``), ``budget`` the flows of fewer RoIs when the object's events
exceed
the budget (see ``TrackerConfig.load.max_searched_per_step``). Each run is a fresh child process,
the
variants interleaved run by run so that the machine's load drifts over all alike; each child
tracks the sequence twice and times the second run (the first loads the compiled kernels).
Oracle poses (1 cm / 0.03 rad noise), as in ``benchmarks/bench_tracker.py``. Printed per
sequence and variant: the median processing time, the real-time factor (processing / sequence
time) and the flow stage's time.

``--frames files memory`` runs each variant twice: with the RGB-D frames decoded from the
sequence's PNG files while tracking (as ``Tracker.track`` on a recording does, in a reader
thread), and with them decoded beforehand, as a live camera delivers them (the tracking
alone). A 640x480 16-bit depth PNG of the simulator takes ~6 ms to decode, 0.35 s per second
of a 60 FPS sequence, on the same two cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tracker_runs import add_run_arguments, compare, run_child, time_tracking

VARIANTS = ("reference", "blas", "strips", "mask", "groups", "kf", "depth", "eq3", "sample",
            "budget", "runs", "long")


def _child(sequence: Path, variant: str, method: str, threads: int, frames: str) -> dict:
    # first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.runtime.openmp_wait)
    import evtrack  # noqa: F401  # isort: skip

    from evtrack.flow.compiled import CompiledSearch
    from evtrack.tracking.silhouette import SilhouettePolygon

    level = VARIANTS.index(variant)
    if level < VARIANTS.index("kf"):
        from evtrack.filters.backends import set_default_backend

        set_default_backend("numpy")
    if level < VARIANTS.index("strips"):
        CompiledSearch.parallel_min_events = 1 << 62
    if level < VARIANTS.index("mask"):
        def point_test(self, x, y, margin, size):
            import numpy as np

            from evtrack.tracking.silhouette import _half_planes

            # the reference: one (N, 2) @ (2, edges) BLAS product, as the tracker had it
            normals, offsets = _half_planes(np.asarray(self.vertices, np.float64))
            xy = np.stack([x, y], 1).astype(np.float64)
            return (xy @ normals.T - offsets).max(axis=1) <= margin

        SilhouettePolygon.contains_pixels = point_test
    if level < VARIANTS.index("runs"):
        from evtrack.tracking.tracker import Tracker

        Tracker.step_runs = False
    if level < VARIANTS.index("depth"):
        from evtrack.tracking import depth_sources

        depth_sources.COMPILED = False
    groups = (40 if level >= VARIANTS.index("long") else
              10 if level >= VARIANTS.index("groups") else 5)
    config = {"method": method, "blas_threads": 0 if level < 1 else 1,
              "flow_batch_steps": groups}
    if level < VARIANTS.index("eq3"):
        config["flow"] = {"max_hypotheses": 48, "max_events_per_roi": 64}
    if level < VARIANTS.index("sample"):
        config.setdefault("load", {})["search_per_roi_window"] = 0
    if level < VARIANTS.index("budget"):
        config.setdefault("load", {})["max_searched_per_step"] = 0
    return time_tracking(sequence, config, threads, frames)


def _spawn(sequence: Path, setting: str, method: str, threads: int) -> dict:
    variant, _, frames = setting.partition("/")
    cmd = [sys.executable, __file__, "--child", "--sequence", str(sequence), "--variants",
           variant, "--method", method, "--threads", str(threads), "--frames", frames or "files"]
    return run_child(cmd, f"{sequence}, {setting}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS,
                    help="which cumulative variants to run (default: all)")
    add_run_arguments(ap, "variant")
    ap.add_argument("--frames", nargs="+", choices=("files", "memory"), default=["files"],
                    help="where the RGB-D frames come from: decoded from the sequence's image "
                         "files while tracking (a recording), or decoded beforehand (a live "
                         "camera: the tracking alone); several: each, side by side")
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(_child(args.sequence[0], args.variants[0], args.method, args.threads,
                                args.frames[0])))
        return 0
    print(f"evtrack.Tracker ({args.method}, {args.threads} threads, oracle poses), cumulative "
          f"CPU changes; median of {args.repeats} interleaved runs, each a fresh process")
    # one setting per variant, or per variant and frame source ("eq3/memory") with several
    settings = (args.variants if len(args.frames) == 1 and args.frames[0] == "files"
                else [f"{v}/{f}" for v in args.variants for f in args.frames])
    compare(args.sequence, settings, "variant", args.repeats,
            lambda seq, name: _spawn(seq, name, args.method, args.threads))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
