"""Write everything an evaluation produced into its results folder.

Layout of ``<out>``::

    results.md, results.csv          tables (evtrack.eval.tables)
    results.yaml                     manifest: pose source, tracker config, sequences, runs,
                                     per-run errors, pose scores (ADD / ADD-S AUC, 5 cm / 5°),
                                     timings and counters, trajectory files
    trajectories/<sequence>/<run>.h5 every trajectory (evtrack.Trajectory.load)
    plots/<sequence>_tracking.png    tracking curves against ground truth
    plots/error_vs_pixel_velocity.png
    plots/pixel_velocity_cdf.png
    videos/<sequence>.mp4            overlay videos (when asked for)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from evtrack.eval.benchmark import ABLATIONS, RunResult, RunSpec
from evtrack.eval.plots import SpeedErrors, plot_error_vs_speed, plot_tracking_curves
from evtrack.eval.samples import pixel_speed_at, sample_errors
from evtrack.eval.sequences import BenchmarkSequence
from evtrack.eval.tables import seed_spreads, write_tables
from evtrack.tracking.trajectory import Trajectory

__all__ = ["ReportFiles", "OUTPUT_NAMES", "write_report", "write_manifest"]

OUTPUT_NAMES = ("results.md", "results.csv", "results.yaml", "trajectories", "plots", "videos")
"""What an evaluation writes into its results folder (the layout above); nothing else there
is its own (:func:`evtrack.utils.claim_output_folder`)."""


@dataclass
class ReportFiles:
    """Paths of what :func:`write_report` wrote, and the Markdown tables."""

    markdown: str
    tables: list[Path] = field(default_factory=list)
    manifest: Path | None = None
    plots: list[Path] = field(default_factory=list)
    videos: list[Path] = field(default_factory=list)


def _rel(path: Path, root: Path) -> str:
    try:
        return path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return str(path)


def write_manifest(path: Path, results: Sequence[RunResult],
                   sequences: Sequence[BenchmarkSequence], runs: Sequence[RunSpec],
                   info: dict[str, Any]) -> Path:
    """``results.yaml``: what was run on what, with every number of the tables."""
    from evtrack.utils import atomic_write_text

    root = path.parent
    data = {
        **info,
        "sequences": [{"name": s.name, "path": str(s.path), "object": s.object_name,
                       "speed": s.speed, **({"split": s.split, "replicate": s.replicate}
                                            if s.split else {})} for s in sequences],
        "runs": [{"name": r.name, "method": r.method, "label": r.label,
                  "overrides": r.overrides} for r in runs],
        "results": [{
            "sequence": r.sequence, "run": r.run, "method": r.method,
            "errors": r.errors.to_dict(),
            "pose_scores": r.scores.to_dict() if r.scores is not None else None,
            "trajectory": _rel(r.trajectory, root),
            "seconds": round(r.seconds, 3), "cpu_seconds": round(r.cpu_seconds, 3),
            "counters": {k: v for k, v in r.stats.items() if k != "time_s"},
            **({"rotations": r.rotations} if r.rotations else {}),
        } for r in results],
    }
    spreads = seed_spreads(results, list(dict.fromkeys(r.run for r in results)))
    if spreads:
        data["seed_spread"] = [sp.to_dict() for sp in spreads]
    atomic_write_text(path, yaml.safe_dump(data, sort_keys=False, allow_unicode=True))
    return path


def write_report(results: Sequence[RunResult], sequences: Sequence[BenchmarkSequence],
                 runs: Sequence[RunSpec], out_dir: str | Path, *, caption: str = "",
                 info: dict[str, Any] | None = None, video: bool = False,
                 video_runs: Sequence[str] | None = None, progress: bool = True
                 ) -> ReportFiles:
    """Tables, manifest, plots and (optionally) overlay videos of an evaluation.

    Args:
        results: from :func:`~evtrack.eval.benchmark.run_benchmark`.
        sequences: the evaluated sequences.
        runs: the evaluated runs (methods and ablations).
        out_dir: results folder.
        caption: the pose source line of the tables.
        info: extra fields of the manifest (pose source, config, command).
        video: write an overlay video per sequence.
        video_runs: runs drawn in the videos (default: ``full`` if evaluated, else the first).
        progress: show progress bars.
    """
    from tqdm import tqdm

    from evtrack.sim.groundtruth import plot_speed_cdf
    from evtrack.sim.objects import load_mesh

    out = Path(out_dir)
    ablation_names = {a.name for a in ABLATIONS}
    methods = [r.name for r in runs if r.name not in ablation_names]
    ablations = [r.name for r in runs if r.name in ablation_names]
    labels = {r.name: r.label for r in runs}
    text = write_tables(results, out, methods, labels, ablations, caption)
    files = ReportFiles(text, [out / "results.md", out / "results.csv"])
    files.manifest = write_manifest(out / "results.yaml", results, sequences, runs,
                                    {"pose_source": caption, **(info or {})})
    by_seq: dict[str, dict[str, RunResult]] = {}
    for r in results:
        by_seq.setdefault(r.sequence, {})[r.run] = r
    pooled: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    speeds: dict[str, list[np.ndarray]] = {}
    if video:
        chosen = list(video_runs) if video_runs else (
            ["full"] if "full" in methods else methods[:1])
    for s in tqdm(sequences, desc="plots", unit="sequence", disable=not progress):
        seq = s.load()
        gt = seq.ground_truth
        mine = by_seq.get(s.name, {})
        trajs = {labels[name]: Trajectory.load(mine[name].trajectory)
                 for name in [*methods, *ablations] if name in mine}
        vertices = load_mesh(seq.mesh_file, recenter=False).vertices
        first = next(iter(trajs.values()), None)
        t_grid = first.t_us.numpy() if first is not None else seq.rgb_times_us.numpy()
        speed = pixel_speed_at(t_grid, gt, vertices, seq.meta.event_camera)
        speeds.setdefault(s.speed or "unknown speed", []).append(speed)
        plot_tracking_curves({k: v for k, v in trajs.items()
                              if k in {labels[m] for m in methods}}, gt,
                             out / "plots" / f"{s.file_stem}_tracking.png",
                             title=f"{s.name} ({s.object_name}, {s.speed or '?'})",
                             pixel_speed=(t_grid, speed))
        files.plots.append(out / "plots" / f"{s.file_stem}_tracking.png")
        for name in (m for m in methods if m in mine):  # the ablations are in Table III
            label, traj = labels[name], trajs[labels[name]]
            err = sample_errors(traj, gt)
            sp = pixel_speed_at(err.t_us, gt, vertices, seq.meta.event_camera)
            pooled.setdefault(label, []).append((sp, err.position_cm, err.rotation_deg))
        if video:
            path = out / "videos" / f"{s.file_stem}.mp4"
            shown = {labels[n]: trajs[labels[n]] for n in chosen if labels.get(n) in trajs}
            from evtrack.eval.video import write_overlay_video

            write_overlay_video(seq, shown, path, progress=progress)
            files.videos.append(path)
    series = {label: SpeedErrors(*(np.concatenate(parts) for parts in zip(*chunks, strict=True)))
              for label, chunks in pooled.items()}
    files.plots.append(plot_error_vs_speed(series, out / "plots" / "error_vs_pixel_velocity.png"))
    cdf = out / "plots" / "pixel_velocity_cdf.png"
    plot_speed_cdf({f"{k} (median {np.median(np.concatenate(v)):.0f} px/s)": np.concatenate(v)
                    for k, v in speeds.items()}, cdf,
                   title="Pixel velocity of the objects, evaluated sequences")
    files.plots.append(cdf)
    return files
