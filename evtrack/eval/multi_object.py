"""Evaluate sequences with several objects: each object tracked together with the others
(:class:`~evtrack.tracking.multi.MultiTracker`) and alone (one
:class:`~evtrack.Tracker` on the same stream), with what occlusion costs.

For every multi-object sequence and method:

* **together**: one multi-object tracker, every object's pose source (or its mesh, with
  ``pose_source: model``), one stream;
* **alone**: each object by a tracker of its own on the same stream (the other objects'
  events are in it: its event gate drops those outside its mask), the same pose source seed;
* **occluded**: the share of the object's silhouette covered by nearer objects' silhouettes
  at the true poses, averaged over the sequence every 10 ms (convex silhouettes: an upper
  bound of the true occlusion);
* **visible / hidden**: the together run's errors over the samples where the object was
  visible (under 5 % hidden) and where it was hidden (at least 25 %): what occlusion costs.

The errors are those of :func:`~evtrack.eval.metrics.tracking_errors` (RMSE over the tracked
samples). The tables give per object ``together / alone`` and their ratio, averaged per
multi-object set and layout, and the processing time of the multi-object tracker beside the
sum of the single trackers' times.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evtrack.errors import ConfigError
from evtrack.eval.benchmark import RunSpec
from evtrack.eval.metrics import TrackingErrors, tracking_errors
from evtrack.eval.pose_setup import PoseSourceSpec, make_pose_source
from evtrack.eval.sequences import BenchmarkSequence
from evtrack.tracking.config import TrackerConfig
from evtrack.utils import atomic_write_text

__all__ = ["ObjectResult", "SequenceTiming", "MULTI_OUTPUT_NAMES", "VISIBLE_BELOW",
           "HIDDEN_FROM", "occlusion_timeline", "occluded_share", "errors_by_occlusion",
           "evaluate_multi_object", "multi_object_tables", "write_multi_object_report"]

MULTI_OUTPUT_NAMES = ("multi_object.md", "multi_object.csv", "multi_object.yaml",
                      "trajectories")
"""What a multi-object evaluation writes into its results folder."""

_OCCLUSION_STEP_US = 10_000

VISIBLE_BELOW = 0.05
"""A sample counts as visible while less than this share of the object is hidden."""

HIDDEN_FROM = 0.25
"""A sample counts as hidden while at least this share of the object is hidden."""


@dataclass
class ObjectResult:
    """One object of one multi-object sequence, one run."""

    sequence: str
    set_name: str
    layout: str
    object_name: str
    run: str
    together: TrackingErrors
    alone: TrackingErrors
    occluded: float
    visible: TrackingErrors | None = None
    hidden: TrackingErrors | None = None


@dataclass
class SequenceTiming:
    """Processing time of one sequence and run (seconds of wall time)."""

    sequence: str
    run: str
    objects: int
    events: int
    together_s: float
    alone_s: float


def occlusion_timeline(sequence, step_us: int = _OCCLUSION_STEP_US
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The share of each object's silhouette (at the true pose) covered by nearer objects'
    silhouettes, every ``step_us`` over the ground truth's time span.

    Returns:
        ``(t_us (T,), shares (K, T))``, shares in [0, 1].
    """
    import cv2

    from evtrack.tracking.silhouette import Silhouette
    from evtrack.tracking.wiring import load_mesh

    cam = sequence.meta.event_camera
    gts = [sequence.object_ground_truth(k) for k in range(len(sequence.objects))]
    sils = [Silhouette(load_mesh(sequence.object_mesh_file(k))[1], cam)
            for k in range(len(gts))]
    t0, t1 = int(gts[0].pose_t_us[0]), int(gts[0].pose_t_us[-1])
    times = np.arange(t0, t1 + 1, step_us, dtype=np.int64)
    shares = np.zeros((len(gts), len(times)))
    for i, t in enumerate(times):
        poses = [gt.pose_at(int(t)).numpy() for gt in gts]
        polys = [s.polygon(p) for s, p in zip(sils, poses, strict=True)]
        for k, poly in enumerate(polys):
            if poly is None or len(poly.vertices) < 3:
                continue
            own = poly.vertices.astype(np.float32)
            area = abs(cv2.contourArea(own))
            if area <= 0:
                continue
            covered = 0.0
            for j, other in enumerate(polys):
                if j == k or other is None or len(other.vertices) < 3:
                    continue
                if poses[j][2, 3] < poses[k][2, 3]:
                    inter, _ = cv2.intersectConvexConvex(own, other.vertices.astype(np.float32))
                    covered += inter
            shares[k, i] = min(covered / area, 1.0)
    return times, shares


def occluded_share(sequence, step_us: int = _OCCLUSION_STEP_US) -> list[float]:
    """Per object, the mean of :func:`occlusion_timeline`'s shares over the sequence."""
    _, shares = occlusion_timeline(sequence, step_us)
    return shares.mean(axis=1).tolist()


def errors_by_occlusion(trajectory, ground_truth, times: np.ndarray, shares: np.ndarray
                        ) -> tuple[TrackingErrors, TrackingErrors]:
    """A trajectory's errors over its samples while the object was visible (under
    :data:`VISIBLE_BELOW` of it hidden) and while it was hidden (at least
    :data:`HIDDEN_FROM`), each sample taking the occlusion of the nearest timeline time (the
    earlier on a tie).

    Args:
        times, shares: one object's :func:`occlusion_timeline` (``shares`` (T,)).
    """
    import torch

    from evtrack.eval.metrics import error_summary, position_errors, rotation_errors

    t = trajectory.t_us.numpy()
    use = (trajectory.tracked & torch.isfinite(trajectory.poses).flatten(1).all(1)).numpy()
    near = np.clip(np.searchsorted(times, t), 0, len(times) - 1)
    left = np.clip(near - 1, 0, len(times) - 1)
    near = np.where(np.abs(times[left] - t) <= np.abs(times[near] - t), left, near)
    share = shares[near]
    out = []
    for part in (share < VISIBLE_BELOW, share >= HIDDEN_FROM):
        pick = torch.from_numpy(use & part)
        if not bool(pick.any()):
            out.append(error_summary(torch.zeros(0), torch.zeros(0), int(part.sum())))
            continue
        est = trajectory.poses[pick]
        true = torch.as_tensor(ground_truth.pose_at(trajectory.t_us[pick]), dtype=torch.float64)
        out.append(error_summary(position_errors(est, true), rotation_errors(est, true),
                                 int(part.sum())))
    return out[0], out[1]


def _sources(spec: PoseSourceSpec, cfg: TrackerConfig, views: list, weights: dict[str, Path]):
    if cfg.pose_source == "model":
        return [None] * len(views)
    return [make_pose_source(spec, v, weights.get(v.meta.object_name),
                             threads=cfg.torch_threads or None) for v in views]


def _starts(cfg: TrackerConfig, views: list) -> tuple[list[Any], int | None]:
    """Start poses (the ground truth's first) for runs with ``pose_source: model``."""
    if cfg.pose_source != "model":
        return [None] * len(views), None
    t0 = int(views[0].ground_truth.pose_t_us[0])
    return [v.ground_truth.pose_at(t0).numpy() for v in views], t0


def evaluate_sequence(sequence: BenchmarkSequence, spec: RunSpec, base: TrackerConfig,
                      pose: PoseSourceSpec, weights: dict[str, Path], out_dir: str | Path,
                      torch_threads: int | None = None
                      ) -> tuple[list[ObjectResult], SequenceTiming]:
    """Track one multi-object sequence together and each object alone (see the module
    docstring); save the trajectories under ``out_dir/trajectories/<sequence>/``."""
    from evtrack.tracking.multi import MultiTracker, TrackedObject
    from evtrack.tracking.tracker import Tracker

    seq = sequence.load()
    cfg = spec.config(base, torch_threads)
    views = [seq.object_view(k) for k in range(len(seq.objects))]
    names = [o.name for o in seq.objects]
    missing = [n for n, v in zip(names, views, strict=True) if v.ground_truth is None]
    if missing:
        raise ConfigError(f"{sequence.path}: object(s) {missing} have no ground truth "
                          "(meta.yaml objects[].ground_truth); the evaluation needs every "
                          "object's")
    starts, t0 = _starts(cfg, views)
    folder = Path(out_dir) / "trajectories" / sequence.file_stem
    multi = MultiTracker([TrackedObject(n, v.mesh_file, s) for n, v, s in zip(
        names, views, _sources(pose, cfg, views, weights), strict=True)], cfg,
        camera=seq.meta.event_camera, rgb_camera=seq.meta.rgb_camera,
        T_event_rgb=seq.meta.T_event_rgb)
    clock = time.perf_counter()
    together = multi.track(seq, start_poses=None if t0 is None else dict(
        zip(names, starts, strict=True)), start_t_us=t0)
    together_s = time.perf_counter() - clock
    alone_s = 0.0
    times, shares = occlusion_timeline(seq)
    results = []
    for k, (name, view, source) in enumerate(zip(names, views, _sources(pose, cfg, views,
                                                                          weights),
                                                 strict=True)):
        tracker = Tracker.for_sequence(view, cfg, source)
        clock = time.perf_counter()
        alone = tracker.track(view, start_pose=starts[k], start_t_us=t0)
        alone_s += time.perf_counter() - clock
        for mode, traj in (("together", together[name]), ("alone", alone)):
            traj.meta.update({"sequence": sequence.name, "run": spec.name, "object": name,
                              "mode": mode})
            traj.save(folder / f"{spec.name}-{name}-{mode}.h5")
        visible, hidden = errors_by_occlusion(together[name], view.ground_truth, times,
                                              shares[k])
        results.append(ObjectResult(
            sequence.name, _set_name(seq), _layout(seq), name, spec.name,
            tracking_errors(together[name], view.ground_truth),
            tracking_errors(alone, view.ground_truth), float(shares[k].mean()), visible,
            hidden))
    timing = SequenceTiming(sequence.name, spec.name, len(names), multi.stats.events,
                            together_s, alone_s)
    return results, timing


def _extra(seq) -> dict:
    extra = seq.meta.extra if isinstance(seq.meta.extra, dict) else {}
    info = extra.get("benchmark")
    return info if isinstance(info, dict) else {}


def _set_name(seq) -> str:
    return str(_extra(seq).get("multi_object_set") or f"{len(seq.objects)} objects")


def _layout(seq) -> str:
    extra = seq.meta.extra if isinstance(seq.meta.extra, dict) else {}
    config = extra.get("config")
    trajectory = config.get("trajectory") if isinstance(config, dict) else None
    layout = trajectory.get("layout") if isinstance(trajectory, dict) else None
    return str(_extra(seq).get("layout") or layout or "")


def _job(args: tuple):
    import torch

    torch.set_num_threads(args[-1] or 1)
    return evaluate_sequence(*args)


def evaluate_multi_object(sequences: list[BenchmarkSequence], runs: list[RunSpec],
                          base: TrackerConfig, pose: PoseSourceSpec, weights: dict[str, Path],
                          out_dir: str | Path, *, jobs: int = 1,
                          torch_threads: int | None = None, progress: bool = True
                          ) -> tuple[list[ObjectResult], list[SequenceTiming]]:
    """Every run on every multi-object sequence (see :func:`evaluate_sequence`); ``jobs``
    worker processes. Timings from parallel jobs share the cores: compare them within a run
    only."""
    from tqdm import tqdm

    from evtrack.utils import threads_per_job

    if jobs > 1:
        torch_threads = threads_per_job(
            base.torch_threads if torch_threads is None else torch_threads, jobs)
    tasks = [(s, r, base, pose, weights, Path(out_dir), torch_threads)
             for s in sequences for r in runs]
    out: list[Any] = [None] * len(tasks)
    bar = tqdm(total=len(tasks), desc="evaluate objects", unit="run", disable=not progress)
    try:
        if jobs == 1:
            for i, task in enumerate(tasks):
                out[i] = evaluate_sequence(*task)
                bar.update(1)
        else:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor, as_completed

            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as pool:
                futures = {pool.submit(_job, task): i for i, task in enumerate(tasks)}
                for fut in as_completed(futures):
                    out[futures[fut]] = fut.result()
                    bar.update(1)
    finally:
        bar.close()
    results = [r for rows, _ in out for r in rows]
    return results, [timing for _, timing in out]


def _pair(e: TrackingErrors | None) -> str:
    if e is None or not e.samples:
        return "—"
    return f"{e.position_rmse_cm:.2f} / {e.rotation_rmse_deg:.2f}"


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}" if b > 0 and np.isfinite(a) and np.isfinite(b) else "—"


def _mean_pair(errors: list[TrackingErrors | None]) -> str:
    """Mean RMSE over the objects with samples, ``(n)`` of them when not all."""
    have = [e for e in errors if e is not None and e.samples]
    if not have:
        return "—"
    p = float(np.mean([e.position_rmse_cm for e in have]))
    r = float(np.mean([e.rotation_rmse_deg for e in have]))
    some = f" ({len(have)})" if len(have) < len(errors) else ""
    return f"{p:.2f} / {r:.2f}{some}"


def _csv_pair(e: TrackingErrors | None) -> list[str]:
    if e is None or not e.samples:
        return ["", ""]
    return [f"{e.position_rmse_cm:.4f}", f"{e.rotation_rmse_deg:.4f}"]


def multi_object_tables(results: list[ObjectResult], timings: list[SequenceTiming]) -> str:
    """The report in Markdown: per object, averages per set and layout, timings."""
    lines = ["## Per object (RMSE cm / deg)", "",
             f"'occluded': the mean share of the object hidden by nearer ones; 'visible' and "
             f"'hidden': the together run's error over the samples where under "
             f"{100 * VISIBLE_BELOW:.0f} % and at least {100 * HIDDEN_FROM:.0f} % of it was "
             "hidden ('—': no such sample).", "",
             "| sequence | run | object | together | alone | ratio (pos / rot) | occluded | "
             "visible | hidden |",
             "|:--|:--|:--|--:|--:|--:|--:|--:|--:|"]
    for r in results:
        lines.append(
            f"| {r.sequence} | {r.run} | {r.object_name} | {_pair(r.together)} | "
            f"{_pair(r.alone)} | {_ratio(r.together.position_rmse_cm, r.alone.position_rmse_cm)}"
            f" / {_ratio(r.together.rotation_rmse_deg, r.alone.rotation_rmse_deg)} | "
            f"{100 * r.occluded:.1f} % | {_pair(r.visible)} | {_pair(r.hidden)} |")
    lines += ["", "## Averages per set and layout (RMSE cm / deg, mean over objects)", "",
              "| set | layout | run | objects | together | alone | ratio (pos / rot) | "
              "occluded | visible | hidden |", "|:--|:--|:--|--:|--:|--:|--:|--:|--:|--:|"]
    groups: dict[tuple[str, str, str], list[ObjectResult]] = {}
    for r in results:
        groups.setdefault((r.set_name, r.layout, r.run), []).append(r)
    for (set_name, layout, run), rows in groups.items():
        def mean(rows, mode, field):
            return float(np.nanmean([getattr(getattr(r, mode), field) for r in rows]))
        tp, tr = mean(rows, "together", "position_rmse_cm"), mean(rows, "together",
                                                                  "rotation_rmse_deg")
        ap, ar = mean(rows, "alone", "position_rmse_cm"), mean(rows, "alone",
                                                               "rotation_rmse_deg")
        occ = float(np.mean([r.occluded for r in rows]))
        lines.append(f"| {set_name} | {layout} | {run} | {len(rows)} | {tp:.2f} / {tr:.2f} | "
                     f"{ap:.2f} / {ar:.2f} | {_ratio(tp, ap)} / {_ratio(tr, ar)} | "
                     f"{100 * occ:.1f} % | {_mean_pair([r.visible for r in rows])} | "
                     f"{_mean_pair([r.hidden for r in rows])} |")
    lines += ["", "## Processing time (s of wall time)", "",
              "| sequence | run | objects | events | together | alone (sum) | ratio |",
              "|:--|:--|--:|--:|--:|--:|--:|"]
    for t in timings:
        lines.append(f"| {t.sequence} | {t.run} | {t.objects} | {t.events} | "
                     f"{t.together_s:.1f} | {t.alone_s:.1f} | "
                     f"{_ratio(t.together_s, t.alone_s)} |")
    return "\n".join(lines) + "\n"


def write_multi_object_report(results: list[ObjectResult], timings: list[SequenceTiming],
                              out_dir: str | Path, caption: str, info: dict[str, Any]) -> str:
    """Write ``multi_object.md``, ``.csv`` and ``.yaml`` (atomically); return the Markdown."""
    import csv
    import io

    import yaml

    out_dir = Path(out_dir)
    markdown = f"# Multi-object evaluation\n\nPose source: {caption}\n\n" + \
        multi_object_tables(results, timings)
    atomic_write_text(out_dir / "multi_object.md", markdown)
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["sequence", "set", "layout", "run", "object", "together_cm",
                     "together_deg", "alone_cm", "alone_deg", "together_tracked",
                     "alone_tracked", "occluded", "visible_cm", "visible_deg", "hidden_cm",
                     "hidden_deg"])
    for r in results:
        writer.writerow([r.sequence, r.set_name, r.layout, r.run, r.object_name,
                         f"{r.together.position_rmse_cm:.4f}",
                         f"{r.together.rotation_rmse_deg:.4f}",
                         f"{r.alone.position_rmse_cm:.4f}", f"{r.alone.rotation_rmse_deg:.4f}",
                         f"{r.together.tracked_fraction:.4f}", f"{r.alone.tracked_fraction:.4f}",
                         f"{r.occluded:.4f}", *_csv_pair(r.visible), *_csv_pair(r.hidden)])
    atomic_write_text(out_dir / "multi_object.csv", buf.getvalue())
    manifest = {**info, "caption": caption,
                "objects": [{"sequence": r.sequence, "run": r.run, "object": r.object_name,
                             "together": r.together.to_dict(), "alone": r.alone.to_dict(),
                             "occluded": r.occluded,
                             "visible": None if r.visible is None else r.visible.to_dict(),
                             "hidden": None if r.hidden is None else r.hidden.to_dict()}
                            for r in results],
                "timings": [vars(t) for t in timings]}
    atomic_write_text(out_dir / "multi_object.yaml", yaml.safe_dump(manifest, sort_keys=False))
    return markdown
