"""Which absolute poses the evaluated tracker gets: a pose network's, or the oracle's.

* ``network``: per object, a weights file found in a folder (searched recursively, e.g.
  ``runs/pose``) or in the shipped zoo (``models/weights``). The network sees the RGB frames
  at its training resolution (``input_scale`` = training width / camera width). It runs in
  torch (``*.pt`` weights) or, with ``backend="onnxruntime"``, on onnxruntime (``*.onnx``
  models written by ``evtrack export``: the deployed form, whose decoded poses equal torch's,
  bit for bit on most frames and within ~1e-6 m and rad on the others, see
  ``models.decode.PNP_GRID_PX``).
* ``oracle``: the sequence's ground-truth pose plus Gaussian noise
  (:class:`~evtrack.tracking.pose_sources.OraclePoseSource`). **Not an estimator**: tables made
  with it
  measure the filters and the velocity pipeline, not a pose network, and say so.
* ``network`` with ``oracle_fallback``: the network where an object has weights, the oracle
  for the objects without (a benchmark whose objects do not all have a trained network yet);
  :func:`pose_caption` names the objects that got the oracle.

Every run of every method on a sequence gets a fresh pose source built from the same
:class:`PoseSourceSpec` (same seed), so the methods see identical pose measurements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from evtrack.errors import ConfigError
from evtrack.tracking.pose_sources import NetworkPoseSource, OraclePoseSource, PoseSource

BACKENDS = {"torch": ".pt", "onnxruntime": ".onnx"}
"""The pose network's backends and the suffix of the files each runs."""

__all__ = ["BACKENDS", "PoseSourceSpec", "find_object_weights", "training_hint", "make_pose_source",
           "pose_caption", "resolve_weights"]


@dataclass(frozen=True)
class PoseSourceSpec:
    """How to build the pose source of a sequence.

    Attributes:
        kind: ``"network"`` or ``"oracle"``.
        weights_dir: folder searched for weights (recursively); ``None``: the shipped zoo.
        weights: one weights file used for every sequence (overrides ``weights_dir``).
        oracle_std_translation: oracle noise per axis, metres.
        oracle_std_rotation: oracle noise per axis (rotation vector), radians.
        seed: seed of the oracle's draws (the network is deterministic).
        depth_refine: refine the network's poses on the RGB-D depth frames
            (:class:`~evtrack.models.DepthRefiner` with the sequence's mesh); the paper's
            pose estimator uses RGB only.
        oracle_fallback: with ``kind="network"``, objects without weights get the oracle
            (with the oracle settings above) instead of an error.
        backend: ``"torch"`` (weights ``*.pt``) or ``"onnxruntime"`` (exported ``*.onnx``
            models), for the weights searched in ``weights_dir`` or the zoo; a ``weights`` file
            runs on the backend its suffix names.
    """

    kind: str = "network"
    weights_dir: Path | None = None
    weights: Path | None = None
    oracle_std_translation: float = 0.01
    oracle_std_rotation: float = 0.03
    seed: int = 0
    depth_refine: bool = False
    oracle_fallback: bool = False
    backend: str = "torch"

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"pose network backend must be one of {sorted(BACKENDS)}, got "
                              f"{self.backend!r}")
        if self.oracle_fallback and self.kind != "network":
            raise ConfigError("--oracle-where-missing falls back from a pose network to the "
                              "oracle; with --oracle every object gets the oracle already")
        if self.depth_refine and self.kind != "network":
            raise ConfigError("--depth-refine refines a pose network's poses; not with --oracle")
        if self.kind not in ("network", "oracle"):
            raise ConfigError(f"pose source kind must be 'network' or 'oracle', got {self.kind!r}")
        for name in ("oracle_std_translation", "oracle_std_rotation"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"--oracle-noise: {name} must be finite and >= 0, got {value}")

    @property
    def oracle_label(self) -> str:
        """The oracle's settings, for captions."""
        cm = 100 * self.oracle_std_translation
        return (f"ORACLE (ground-truth poses + Gaussian noise {cm:g} cm, "
                f"{math.degrees(self.oracle_std_rotation):.3g} deg per axis, seed {self.seed})")

    @property
    def label(self) -> str:
        """One line for table captions."""
        if self.kind == "oracle":
            return f"{self.oracle_label}: measures the tracker's filters, not a pose network"
        refine = " + depth refinement (ICP on the RGB-D depth)" if self.depth_refine else ""
        if self.weights is not None:
            return f"pose network {self.weights}{refine}"
        where = self.weights_dir if self.weights_dir is not None else "the shipped zoo"
        kind = "ONNX models" if self.backend == "onnxruntime" else "weights"
        return f"pose network ({kind} per object from {where}){refine}"


def training_hint(object_name: str) -> str:
    """The command that trains weights for ``object_name``."""
    from evtrack.sim.objects import PROCEDURAL_OBJECTS, YCB_OBJECTS

    if object_name in YCB_OBJECTS:
        return f"evtrack train --config configs/pose_ycb_{object_name}.yaml"
    if object_name in ("box", "coded_box"):
        return f"evtrack train --config configs/pose_demo_{object_name}.yaml"
    if object_name in PROCEDURAL_OBJECTS:
        return (f"evtrack train --config configs/pose_demo_box.yaml "
                f"--set object.name={object_name}")
    return "evtrack train with a config for it (see configs/pose_*.yaml)"


def find_object_weights(object_name: str, folder: str | Path | None = None,
                        arch: str | None = None, backend: str = "torch") -> Path:
    """A weights file trained on ``object_name``, of any (or the given) architecture.

    Searches ``folder`` recursively for ``*.pt`` weights files (``backend="onnxruntime"``:
    ``*.onnx`` models written by ``evtrack export``, read by their embedded record; default
    folder: the shipped zoo, ``models/weights``). With several matches, the most recently
    created record wins (then the path order).

    Raises:
        ConfigError: none found, saying how to train them or to use the oracle, and naming
            the other backend when it has files for the object there.
    """
    from evtrack.models.weights import zoo_dir

    if backend not in BACKENDS:
        raise ConfigError(f"pose network backend must be one of {sorted(BACKENDS)}, got "
                          f"{backend!r}")
    root = Path(folder) if folder is not None else zoo_dir()
    hits = _matching_files(root, BACKENDS[backend], object_name, arch)
    if not hits:
        wanted = f"object {object_name!r}" + (f" and architecture {arch!r}" if arch else "")
        other = next(b for b in BACKENDS if b != backend)
        if _matching_files(root, BACKENDS[other], object_name, arch):
            how = ("export them with 'evtrack export pose --weights W.pt --out W.onnx', or "
                   if backend == "onnxruntime" else "")
            raise _OtherBackendOnly(
                f"no {BACKENDS[backend]} pose-network files for {wanted} in {root}, but "
                f"{BACKENDS[other]} ones: {how}pass --backend {other}")
        if backend == "onnxruntime":
            raise ConfigError(
                f"no .onnx pose-network models for {wanted} in {root}; export trained weights "
                "with 'evtrack export pose --weights W.pt --out DIR/W.onnx' and pass "
                "--weights-dir DIR, or run them in torch (--backend torch)")
        raise ConfigError(
            f"no pose-network weights for {wanted} in {root}; train them with "
            f"'{training_hint(object_name)}' (then copy the .pt into models/weights or pass "
            "its folder with --weights-dir), or pass --oracle to use ground-truth poses with "
            "noise instead")
    hits.sort(key=lambda h: h[:3])
    return hits[-1][3]


class _OtherBackendOnly(ConfigError):
    """No files of the asked backend for an object, but files of the other: a wrong
    ``--backend``, never a reason for the oracle fallback."""


def _matching_files(root: Path, suffix: str, object_name: str, arch: str | None
                    ) -> list[tuple[str, bool, str, Path]]:
    """``(created, full precision, path text, path)`` of the files ``*suffix`` under ``root``
    whose record names ``object_name`` (and ``arch``); files without a readable record are
    skipped. Sorted, the last is the one to use: the newest record, at equal records (an FP32
    and an FP16 export of the same weights) the full-precision one, then the path order."""
    from evtrack.models.weights import WeightsError, read_record

    hits = []
    if not root.is_dir():
        return hits
    for path in sorted(root.rglob(f"*{suffix}")):
        try:
            record, precision = read_record(path)
        except WeightsError:
            continue  # not a weights file (e.g. an unrelated tensor dump)
        if (record is not None and record.object_name == object_name
                and (arch is None or record.arch == arch)):
            hits.append((record.created, precision != "fp16", str(path), path))
    return hits


def resolve_weights(spec: PoseSourceSpec, objects: list[str]) -> dict[str, Path]:
    """The weights file of each object (empty for the oracle); raises before any work.

    With ``spec.oracle_fallback`` an object without weights is left out (it gets the oracle,
    see :func:`make_pose_source`) instead of raising.
    """
    if spec.kind == "oracle":
        return {}
    if spec.weights is not None:
        if not Path(spec.weights).is_file():
            raise ConfigError(f"--weights {spec.weights}: file not found")
        return {name: Path(spec.weights) for name in objects}
    found = {}
    for name in sorted(set(objects)):
        try:
            found[name] = find_object_weights(name, spec.weights_dir,
                                              backend=spec.backend)
        except _OtherBackendOnly:
            raise  # weights that run on the other backend: a wrong --backend, not a gap
        except ConfigError:
            if not spec.oracle_fallback:
                raise
    for path in found.values():
        if path.suffix.lower() == ".onnx":
            _check_onnx_loads(path)
    return found


def _check_onnx_loads(path: Path) -> None:
    """Open ``path`` in onnxruntime once, so that a model whose graph is broken (its record
    reads fine) is an error before any tracking, not in the middle of a benchmark."""
    import onnxruntime as ort

    try:
        ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types
        raise ConfigError(f"{path}: onnxruntime cannot load the model ({exc}); export it "
                          "again with 'evtrack export pose'") from None


def pose_caption(spec: PoseSourceSpec, weights: dict[str, Path], objects: list[str]) -> str:
    """The table caption: :attr:`PoseSourceSpec.label`, and with ``oracle_fallback`` the
    objects (of ``objects``) that got the oracle for want of weights."""
    missing = sorted(set(objects) - set(weights)) if spec.kind == "network" else []
    if not missing:
        return spec.label
    return (f"{spec.label}; {spec.oracle_label} for {', '.join(missing)} (no weights): those "
            "rows measure the tracker's filters, not a pose network")


def make_pose_source(spec: PoseSourceSpec, sequence, weights: Path | None = None,
                     threads: int | None = None) -> PoseSource:
    """A fresh pose source for ``sequence`` (a :class:`~evtrack.Sequence`).

    Args:
        spec: the kind of source and its settings.
        sequence: the sequence (its ground truth for the oracle, its RGB camera for a network).
        weights: the network's weights file (from :func:`resolve_weights`): ``*.onnx`` runs
            on onnxruntime, anything else in torch.
        threads: onnxruntime's intra-op CPU threads (``None``: its own choice); torch's are
            the tracker's ``torch_threads``.
    """
    if spec.kind == "oracle" or (weights is None and spec.oracle_fallback):
        return OraclePoseSource.from_sequence(
            sequence, std_translation=spec.oracle_std_translation,
            std_rotation=spec.oracle_std_rotation, seed=spec.seed)
    if weights is None:
        raise ConfigError("a network pose source needs a weights file")
    from evtrack.models import OnnxPoseEstimator, TorchPoseEstimator
    from evtrack.models.weights import read_record

    cam = sequence.meta.rgb_camera or sequence.meta.event_camera
    name = sequence.meta.object_name
    record, _ = read_record(weights)
    scale = record.input_size[1] / cam.width if record is not None else None
    if Path(weights).suffix.lower() == ".onnx":
        # no spinning threads: the network shares the cores with the tracking between calls
        est = OnnxPoseEstimator(weights, cam, object_name=name, input_scale=scale,
                                threads=threads, spin=False)
    else:
        est = TorchPoseEstimator.from_weights(weights, cam, object_name=name,
                                              input_scale=scale)
    refiner = None
    if spec.depth_refine:
        from evtrack.models import DepthRefiner

        refiner = DepthRefiner.from_mesh(sequence.mesh_file)
    return NetworkPoseSource(est, sequence.meta.T_event_rgb, refiner=refiner, camera=cam)
