"""Run tracking methods over benchmark sequences and collect their errors.

Each (sequence, run) pair is independent: a fresh :class:`~evtrack.Tracker` with a fresh pose
source built from the same :class:`~evtrack.eval.pose_setup.PoseSourceSpec` (same seed), so
every method sees the same pose measurements and results do not depend on the order or on how
many worker processes run them. Each trajectory is measured twice: RMSE and σ of its tracked
samples (:func:`~evtrack.eval.metrics.tracking_errors`), and the ADD / ADD-S AUC and 5 cm / 5°
share of all its samples (:func:`~evtrack.eval.pose_auc.sequence_pose_scores`). It is saved as
``<out>/trajectories/<sequence>/<run>.h5`` (:meth:`~evtrack.Trajectory.save`), so plots and
tables can be redone without tracking again.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from evtrack.errors import ConfigError
from evtrack.eval.metrics import TrackingErrors, tracking_errors
from evtrack.eval.pose_auc import PoseScores, sequence_pose_scores
from evtrack.eval.pose_setup import PoseSourceSpec, make_pose_source
from evtrack.eval.sequences import BenchmarkSequence
from evtrack.tracking.config import METHODS, TrackerConfig
from evtrack.utils import threads_per_job

__all__ = ["RunSpec", "RunResult", "ABLATIONS", "DEFAULT_METHODS", "MESH_ONLY_RUNS", "run_specs",
           "run_one", "run_benchmark", "trajectory_path", "pose_warnings", "rotation_notes",
           "start_pose"]

#: Methods in the default column order (the paper's "Ours (OF)" first).
DEFAULT_METHODS = ("full", "velocity", "pose", "ge", "frame-flow")


@dataclass(frozen=True)
class RunSpec:
    """One column of the tables: a tracking method, possibly with config changes.

    Attributes:
        name: identifier, also the trajectory's file stem (``full``, ``full-no-weighting``).
        method: :attr:`TrackerConfig.method`.
        label: text for tables and legends.
        overrides: nested config changes applied on top of the base config.
    """

    name: str
    method: str
    label: str
    overrides: dict[str, Any] = field(default_factory=dict)

    def config(self, base: TrackerConfig, torch_threads: int | None = None) -> TrackerConfig:
        changes: dict[str, Any] = {"method": self.method, **self.overrides}
        if torch_threads is not None:
            changes["torch_threads"] = torch_threads
        # from_dict merges a section's fields into the base's section
        return TrackerConfig.from_dict(changes, f"run {self.name}", base=base)


#: Ablations of the full method (the paper's Table III), and three extensions (not in the
#: paper): the pose filter's velocity bias (``pose_ukf.velocity_bias``), the range of every
#: depth frame fused into the pose filter (``depth_fusion.range``), and the mesh aligned with
#: the depth frames (``depth_fusion.icp``).
ABLATIONS = (
    RunSpec("full-no-normal-flow", "full", "full w/o normal-flow constraint",
            {"velocity_kf": {"normal_flow": False}}),
    RunSpec("full-no-weighting", "full", "full w/o measurement weighting",
            {"velocity_kf": {"weighting": False}}),
    RunSpec("full-velocity-bias", "full", "full + velocity bias (not in the paper)",
            {"pose_ukf": {"velocity_bias": True}}),
    RunSpec("full-depth-range", "full", "full + depth range (not in the paper)",
            {"depth_fusion": {"range": True}}),
    RunSpec("full-depth-icp", "full", "full + depth alignment (not in the paper)",
            {"depth_fusion": {"icp": True}}),
)


#: The full method with poses from the object's mesh alone (``pose_source: model``, nothing
#: trained, not in the paper), started from the ground truth's first pose: with the RGB-D
#: frames (depth alignment and appearance), and with the RGB frames only (appearance, the RoIs'
#: depth rendered from the mesh).
MESH_ONLY_RUNS = (
    RunSpec("full-model", "full", "full, mesh only (RGB-D; not in the paper)",
            {"pose_source": "model"}),
    RunSpec("full-model-rgb", "full", "full, mesh only (RGB; not in the paper)",
            {"pose_source": "model", "depth": {"source": "model"}}),
)


def start_pose(spec: RunSpec, base: TrackerConfig, sequence) -> tuple[Any, int | None]:
    """``(pose (4, 4), t_us)`` a run starts from: the ground truth's first pose for a run
    whose poses come from the mesh (``pose_source: model``: a user gives it the start pose),
    ``(None, None)`` for the others (they start on their first pose)."""
    if spec.config(base).pose_source != "model":
        return None, None
    gt = sequence.ground_truth
    t0 = int(gt.pose_t_us[0])
    return gt.pose_at(t0), t0


def run_specs(methods: Iterable[str] = DEFAULT_METHODS, ablation: bool = False
              ) -> list[RunSpec]:
    """The runs of an evaluation: one per method, plus the ablations of ``full``.

    Raises:
        ConfigError: an unknown or repeated method.
    """
    methods = list(methods)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ConfigError(f"unknown method(s) {unknown}; known: {list(METHODS)}")
    if len(set(methods)) != len(methods):
        raise ConfigError(f"methods repeated: {methods}")
    if not methods:
        raise ConfigError("no method to evaluate")
    runs = [RunSpec(m, m, m) for m in methods]
    if ablation:
        if "full" not in methods:
            runs.insert(0, RunSpec("full", "full", "full"))
        runs += list(ABLATIONS)
    return runs


@dataclass
class RunResult:
    """The outcome of one run on one sequence.

    Attributes:
        sequence: the sequence's name; object_name, speed: its labels.
        run: :attr:`RunSpec.name`; method: the tracking method.
        errors: RMSE and σ of the tracked samples (cm, deg).
        trajectory: the saved trajectory file.
        seconds: wall time of the tracking, seconds.
        cpu_seconds: CPU time of the tracking process meanwhile, seconds.
        stats: the tracker's counters (:class:`~evtrack.tracking.tracker.TrackerStats` as a dict).
        scores: ADD / ADD-S AUC (%) and 5 cm / 5° share (%) over all samples, the untracked
            ones failing (:class:`~evtrack.eval.pose_auc.PoseScores`); ``None``: not measured.
        split, replicate: the sequence's split and seed index (see
            :class:`~evtrack.eval.sequences.BenchmarkSequence`).
        rotations: the rotations the frame alignments observed
            (:meth:`RotationObservability.to_dict
            <evtrack.tracking.observability.RotationObservability.to_dict>`: alignments per
            source, the unobserved object axes); empty without frame alignments.
    """

    sequence: str
    object_name: str
    speed: str
    run: str
    method: str
    errors: TrackingErrors
    trajectory: Path
    seconds: float
    cpu_seconds: float = 0.0
    stats: dict[str, Any] = field(default_factory=dict)
    scores: PoseScores | None = None
    split: str = ""
    replicate: int | None = None
    rotations: dict[str, Any] = field(default_factory=dict)


def trajectory_path(out_dir: str | Path, sequence: BenchmarkSequence, run: str) -> Path:
    """Where the trajectory of ``run`` on ``sequence`` is saved."""
    return Path(out_dir) / "trajectories" / sequence.file_stem / f"{run}.h5"


def run_one(sequence: BenchmarkSequence, spec: RunSpec, base: TrackerConfig,
            pose: PoseSourceSpec, weights: Path | None, out_dir: str | Path,
            torch_threads: int | None = None) -> RunResult:
    """Track ``sequence`` with one run, save the trajectory, measure its errors and scores
    (the scores' nearest-point queries use the run's torch threads)."""
    from evtrack.tracking.tracker import Tracker

    seq = sequence.load()
    cfg = spec.config(base, torch_threads)
    source = (None if cfg.pose_source == "model"
              else make_pose_source(pose, seq, weights, threads=cfg.torch_threads or None))
    tracker = Tracker.for_sequence(seq, cfg, source)
    start, start_t = start_pose(spec, base, seq)
    t0, c0 = time.perf_counter(), time.process_time()
    traj = tracker.track(seq, start_pose=start, start_t_us=start_t)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    label = ("the object's mesh, from the ground truth's first pose"
             if cfg.pose_source == "model" else pose.label)
    traj.meta.update({"sequence": sequence.name, "run": spec.name, "pose_source": label})
    path = trajectory_path(out_dir, sequence, spec.name)
    traj.save(path)
    scores = sequence_pose_scores(traj, seq, workers=threads_per_job(cfg.torch_threads))
    return RunResult(sequence.name, sequence.object_name, sequence.speed, spec.name, spec.method,
                     tracking_errors(traj, seq.ground_truth), path, seconds, cpu,
                     tracker.stats.to_dict(), scores, sequence.split, sequence.replicate,
                     tracker.observability.to_dict() if tracker.observability.alignments
                     else {})


def _run_job(args: tuple) -> RunResult:
    import torch

    threads = args[-1]
    torch.set_num_threads(threads if threads else 1)
    return run_one(*args)


def run_benchmark(sequences: list[BenchmarkSequence], runs: list[RunSpec],
                  base: TrackerConfig, pose: PoseSourceSpec, weights: dict[str, Path],
                  out_dir: str | Path, *, jobs: int = 1, torch_threads: int | None = None,
                  progress: bool = True) -> list[RunResult]:
    """Every run on every sequence; results in (sequence, run) order.

    Args:
        sequences: from :func:`~evtrack.eval.sequences.find_sequences`.
        runs: from :func:`run_specs`.
        base: the tracker config every run starts from.
        pose: the pose source of every run.
        weights: object -> weights file (:func:`~evtrack.eval.pose_setup.resolve_weights`).
        out_dir: results folder (trajectories go under ``trajectories/``).
        jobs: worker processes (1: in this process).
        torch_threads: torch CPU threads per run (``None``: the config's ``torch_threads``);
            with several jobs, at most each job's share of the cores
            (:func:`~evtrack.utils.threads_per_job`), since oversubscribed threads are far slower.
        progress: show a tqdm bar.
    """
    from tqdm import tqdm

    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    if jobs > 1:
        torch_threads = threads_per_job(
            base.torch_threads if torch_threads is None else torch_threads, jobs)
    tasks = [(s, r, base, pose, weights.get(s.object_name), Path(out_dir), torch_threads)
             for s in sequences for r in runs]
    bar = tqdm(total=len(tasks), desc="evaluate", unit="run", disable=not progress)
    results: list[RunResult | None] = [None] * len(tasks)
    try:
        if jobs == 1:
            for i, task in enumerate(tasks):
                bar.set_postfix_str(f"{task[0].name}: {task[1].name}")
                results[i] = run_one(*task)
                bar.update(1)
        else:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor, as_completed

            ctx = multiprocessing.get_context("spawn")
            pool = ProcessPoolExecutor(max_workers=jobs, mp_context=ctx)
            try:
                futures = {pool.submit(_run_job, task): i for i, task in enumerate(tasks)}
                for fut in as_completed(futures):
                    i = futures[fut]
                    results[i] = fut.result()
                    bar.set_postfix_str(f"{tasks[i][0].name}: {tasks[i][1].name}")
                    bar.update(1)
            finally:
                pool.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()
    return [r for r in results if r is not None]


def rotation_notes(results: Iterable[RunResult]) -> list[str]:
    """One line per run whose frame alignments left a rotation of the object unobserved
    (:meth:`Tracker.unobserved_rotations
    <evtrack.tracking.tracker.Tracker.unobserved_rotations>`): its error about that axis
    comes from the events and the pose source alone."""
    from evtrack.tracking.observability import UnobservedRotation

    lines = []
    for r in results:
        for u in r.rotations.get("unobserved", ()):
            axis = UnobservedRotation(np.asarray(u["axis"], np.float64), u["std_deg"])
            lines.append(f"note: {r.sequence} ({r.run}): the frame alignments did not observe "
                         f"the rotation {axis.describe()}")
    return lines


def pose_warnings(results: Iterable[RunResult]) -> list[str]:
    """One line per sequence whose pose source returned no pose at all (nothing can be
    tracked then: every method starts from a pose)."""
    lines, seen = [], set()
    for r in results:
        calls, poses = r.stats.get("pose_calls", 0), r.stats.get("poses", 0)
        if calls and not poses and r.sequence not in seen:
            seen.add(r.sequence)
            lines.append(f"warning: {r.sequence}: the pose source found the object in none of "
                         f"its {calls} frames, so no method tracked anything (check the pose "
                         "network's weights, or use --oracle)")
    return lines
