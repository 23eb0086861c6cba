"""``evtrack demo``: simulate a fast object, track it three ways, show how well each did.

Steps (each reusing the library):

1. Simulate a short ``faster``-preset sequence of the shipped procedural object ``coded_box``
   (a box with colour-coded corners, texture seed 0, the texture the shipped pose network was
   trained on) with :mod:`evtrack.sim`.
2. Track it with the methods ``velocity``, ``pose`` and ``full`` (:class:`evtrack.Tracker`),
   poses at 5 Hz from the shipped pose-network weights for ``coded_box`` (or ``--oracle``).
3. Write the tables, trajectories, plots and an overlay video (:mod:`evtrack.eval.report`)
   and print the RMSE of each method against the ground truth.

The defaults (320x240, 1.5 s) keep the whole demo under a minute on 2 CPU cores; the flow's
RoI size is scaled with the image width (32 px at 640 px wide). The renders feeding the event
model run at ``render_hz`` = 4 kHz, not the paper's 500 Hz: the event model interpolates the log
intensity between renders, so at 500 Hz an edge moving several pixels per render gets event times
off by up to 2 ms, which real sensors do not have and which the triplet flow (built on event
timing) pays for (on the demo's sequence with oracle poses: RoI flow error 56 % -> 23 %, ``full``
10.5 cm / 30° -> 5.1 cm / 19°).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from evtrack.errors import ConfigError, EvtrackError
from evtrack.eval.benchmark import RunResult, RunSpec, run_benchmark
from evtrack.eval.pose_setup import PoseSourceSpec, find_object_weights
from evtrack.eval.report import ReportFiles, write_report
from evtrack.eval.sequences import find_sequences
from evtrack.eval.tables import Cell
from evtrack.tracking.config import TrackerConfig

__all__ = ["DemoOptions", "DemoResult", "run_demo", "demo_weights", "demo_tracker_config",
           "DEMO_OBJECT", "DEMO_METHODS", "summary_table"]

DEMO_OBJECT = "coded_box"
"""The shipped procedural object the demo tracks (:func:`evtrack.sim.objects.make_coded_box`)."""
DEMO_TRAINING_CONFIG = "configs/pose_demo_coded_box.yaml"
"""The config that trains the shipped weights for it."""
DEMO_OBJECT_SEED = 0
"""Its texture seed: the one the shipped weights were trained on."""
DEMO_PRESET = "faster"
DEMO_RENDER_HZ = 4000.0
"""Render rate feeding the event model (see the module docstring)."""
DEMO_METHODS = ("velocity", "pose", "full")
DEMO_LABELS = {"velocity": "velocity (events only)", "pose": "pose (5 Hz poses only)",
               "full": "full (events + poses)"}
REFERENCE_WIDTH = 640
"""The demo's pixel settings are stated at this image width and scaled to its own width."""
DEMO_ROI_AT_REFERENCE = 32
"""The flow's RoI size for the demo object at 640 px (16 px at the demo's 320 px). Larger than
the tracker's default (12 px, tuned on the YCB benchmark): the coded box's faces are flat
colour quadrants, so its events come from few borders and small RoIs hold too few of them
(demo sequence, shipped weights, full method: 4.1 cm / 16.8 deg with 16 px RoIs, 3.7 / 17.7
with 12 px, 10.3 / 24.1 with 8 px)."""
MIN_ROI = 8


@dataclass
class DemoOptions:
    """Settings of the demo.

    Attributes:
        out: output folder.
        duration: simulated seconds.
        size: ``(width, height)`` of the simulated cameras, pixels.
        weights: pose-network weights for ``coded_box`` (default: the shipped ones).
        oracle: use ground-truth poses with noise (1 cm, 0.03 rad) instead of a network.
        depth_refine: refine the network's poses on the depth frames (ICP with the mesh).
        depth_range: fuse the object's range measured on each depth frame into the pose
            filter (the tracker's ``depth_fusion.range``; not the paper's method).
        depth_icp: align the mesh with the depth frames and fuse the aligned poses (the
            tracker's ``depth_fusion.icp``; not the paper's method).
        seed: seed of the trajectory, the scene, the sensor noise and the oracle.
        overwrite: replace the outputs of an earlier demo in ``out``.
        jobs: worker processes tracking the methods in parallel.
        progress: show progress bars.
    """

    out: Path = Path("evtrack-demo")
    duration: float = 1.5
    size: tuple[int, int] = (320, 240)
    weights: Path | None = None
    oracle: bool = False
    depth_refine: bool = False
    depth_range: bool = False
    depth_icp: bool = False
    seed: int = 0
    overwrite: bool = False
    jobs: int = field(default_factory=lambda: min(2, os.cpu_count() or 1))
    progress: bool = True

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if not (self.duration > 0.5):
            raise ConfigError(f"--duration must be > 0.5 s (the poses arrive 0.2 s late), "
                              f"got {self.duration}")
        w, h = self.size
        if w < 32 or h < 24:
            raise ConfigError(f"--size must be at least 32x24, got {w}x{h}")
        if self.oracle and self.weights is not None:
            raise ConfigError("give either --weights or --oracle, not both")
        if self.oracle and self.depth_refine:
            raise ConfigError("--depth-refine refines a pose network's poses; not with --oracle")
        if self.jobs < 1:
            raise ConfigError(f"--jobs must be >= 1, got {self.jobs}")


@dataclass
class DemoResult:
    """What the demo made: the sequence folder, per-method results, files, stage timings (s)."""

    sequence: Path
    results: list[RunResult]
    files: ReportFiles
    pose_source: str
    seconds: dict[str, float]


def demo_weights(weights: Path | None = None) -> Path:
    """The pose-network weights for the demo object: ``weights`` checked (``.pt`` weights, or
    an ``.onnx`` model from ``evtrack export pose``, which then runs on onnxruntime), or the
    shipped ones.

    Raises:
        ConfigError: none shipped (saying how to make them or to use ``--oracle``), or a file
            trained on another object.
    """
    from evtrack.models.weights import read_record, zoo_dir

    if weights is not None:
        record, _ = read_record(weights)
        if record is None:
            raise ConfigError(f"--weights {weights}: the model carries no weights record "
                              "(export it with 'evtrack export pose')")
        if record.object_name != DEMO_OBJECT:
            raise ConfigError(f"--weights {weights}: trained on {record.object_name!r}, the demo "
                              f"tracks {DEMO_OBJECT!r}")
        return Path(weights)
    try:
        return find_object_weights(DEMO_OBJECT)
    except ConfigError:
        raise ConfigError(
            f"no shipped pose-network weights for the demo object {DEMO_OBJECT!r} in "
            f"{zoo_dir()}. Train them with 'evtrack train --config {DEMO_TRAINING_CONFIG}' "
            f"and pass the result with --weights runs/pose/{DEMO_OBJECT}_dope_lite_small/"
            f"{DEMO_OBJECT}_dope_lite_small.pt (or copy it into that folder), or run 'evtrack "
            "demo --oracle' to use ground-truth poses with noise instead of a network") from None


def demo_tracker_config(width: int, depth_range: bool = False, depth_icp: bool = False
                        ) -> TrackerConfig:
    """Tracker defaults with the demo's RoI size (``DEMO_ROI_AT_REFERENCE``, at least
    ``MIN_ROI``) and the default mask margin, both scaled from 640 px to the image width;
    ``depth_fusion.range`` and ``depth_fusion.icp`` set the tracker's ``depth_fusion.range`` and
    ``depth_fusion.icp`` (off by default, as in the paper)."""
    default = TrackerConfig()
    scale = width / REFERENCE_WIDTH
    roi = max(MIN_ROI, round(DEMO_ROI_AT_REFERENCE * scale))
    return TrackerConfig.from_dict(
        {"flow": {"roi_size": roi}, "mask_margin_px": default.mask_margin_px * scale,
         "depth_fusion": {"range": bool(depth_range), "icp": bool(depth_icp)}},
        "demo tracker config")


def _simulate(opts: DemoOptions, folder: Path) -> None:
    from evtrack.sim.config import GroundTruthConfig, RenderConfig, SimConfig, TrajectoryConfig
    from evtrack.sim.engine import simulate
    from evtrack.sim.objects import procedural_object

    cfg = SimConfig(duration=float(opts.duration), seed=int(opts.seed),
                    trajectory=TrajectoryConfig(preset=DEMO_PRESET),
                    render=RenderConfig(render_hz=DEMO_RENDER_HZ),
                    ground_truth=GroundTruthConfig(event_flow=False))
    cfg = dataclasses.replace(cfg, camera=cfg.camera.resized(*opts.size))
    simulate(procedural_object(DEMO_OBJECT, DEMO_OBJECT_SEED), cfg, folder,
             overwrite=opts.overwrite, progress=opts.progress)


def _check_out(opts: DemoOptions) -> None:
    out = opts.out
    if out.exists() and not out.is_dir():
        raise EvtrackError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not opts.overwrite:
        raise EvtrackError(f"{out} exists and is not empty; pass --overwrite to replace the "
                           "demo's outputs there, or choose another --out")


def summary_table(results: list[RunResult], labels: dict[str, str]) -> str:
    """A plain-text table: method, position and rotation RMSE ± σ, tracked share."""
    head = f"{'method':<28} {'position (cm)':>15} {'rotation (deg)':>15} {'tracked':>8}"
    lines = [head, "-" * len(head)]
    for r in results:
        e = r.errors
        lines.append(f"{labels.get(r.run, r.run):<28} "
                     f"{Cell(e.position_rmse_cm, e.position_std_cm).text():>15} "
                     f"{Cell(e.rotation_rmse_deg, e.rotation_std_deg).text():>15} "
                     f"{100 * e.tracked_fraction:>7.0f}%")
    return "\n".join(lines)


def run_demo(opts: DemoOptions, log=print) -> DemoResult:
    """Run the demo (see the module docstring); ``log`` prints the progress lines."""
    t_start = time.perf_counter()
    _check_out(opts)
    if opts.oracle:
        spec, weights = PoseSourceSpec("oracle", seed=opts.seed), None
    else:
        weights = demo_weights(opts.weights)
        spec = PoseSourceSpec("network", weights=weights, seed=opts.seed,
                              depth_refine=opts.depth_refine)
    w, h = opts.size
    seq_dir = opts.out / f"{DEMO_OBJECT}_{DEMO_PRESET}"
    seconds: dict[str, float] = {}
    log(f"[1/3] simulating {opts.duration:g} s of the '{DEMO_OBJECT}' moving fast "
        f"({DEMO_PRESET} preset), {w}x{h}, seed {opts.seed} -> {seq_dir}")
    t0 = time.perf_counter()
    _simulate(opts, seq_dir)
    seconds["simulate"] = time.perf_counter() - t0
    sequences = find_sequences(seq_dir)
    runs = [RunSpec(m, m, DEMO_LABELS[m]) for m in DEMO_METHODS]
    log(f"[2/3] tracking with {', '.join(DEMO_METHODS)}; pose source: {spec.label}")
    t0 = time.perf_counter()
    config = demo_tracker_config(w, opts.depth_range, opts.depth_icp)
    results = run_benchmark(sequences, runs, config, spec,
                            {DEMO_OBJECT: weights} if weights else {}, opts.out,
                            jobs=min(opts.jobs, len(runs)), progress=opts.progress)
    seconds["track"] = time.perf_counter() - t0
    log("[3/3] writing tables, plots and the overlay video")
    t0 = time.perf_counter()
    files = write_report(results, sequences, runs, opts.out, caption=spec.label,
                         info={"demo": {k: str(v) for k, v in dataclasses.asdict(opts).items()}},
                         video=True, video_runs=list(DEMO_METHODS), progress=opts.progress)
    seconds["report"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - t_start
    return DemoResult(seq_dir, results, files, spec.label, seconds)
