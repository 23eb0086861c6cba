"""Weights files and their records (the model zoo's format), loaded with ``weights_only=True``.

A weights file is a ``torch.save``-d dict of plain types and tensors only::

    {"format": "evtrack.pose_weights", "format_version": 1,
     "record": WeightsRecord.to_dict(), "state_dict": {name: Tensor}}

so that ``torch.load(path, weights_only=True)`` reads it without unpickling code. Lightning
checkpoints written by ``evtrack train`` are accepted too: their hyper-parameters hold the same
record (see :class:`evtrack.train.module.PoseLightningModule`) and their state dict the network
under the ``net.`` prefix.

Shipped weights live in ``models/weights/<file>.pt`` with a model card ``<file>.md`` beside.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import torch
import yaml

from evtrack.errors import ConfigError, EvtrackError
from evtrack.models.cuboid import Cuboid

__all__ = [
    "WeightsError",
    "WeightsRecord",
    "save_weights",
    "set_record_decode",
    "load_weights_file",
    "read_record",
    "zoo_dir",
    "list_weights",
    "find_default_weights",
    "model_card",
    "write_model_card",
    "FORMAT",
    "FORMAT_VERSION",
]

FORMAT = "evtrack.pose_weights"
FORMAT_VERSION = 1
LIGHTNING_PREFIX = "net."
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class WeightsError(EvtrackError, ValueError):
    """A weights or checkpoint file that cannot be used: wrong format, architecture or object."""

    def __init__(self, path: object, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self) -> tuple:
        # rebuilt from its arguments (the default would pass the message as ``path``), so
        # that the error crosses process boundaries (evaluate --jobs)
        return type(self), (self.path, self.problem)


@dataclass
class WeightsRecord:
    """Everything needed to use a set of weights, stored alongside its state dict.

    Attributes:
        arch: registered model name (``evtrack.models.list_models()``).
        arch_kwargs: keyword hyper-parameters given to the entry point.
        object_name: the object the network was trained on.
        cuboid: that object's cuboid (dimensions and centre in the mesh frame, metres).
        input_size: ``(height, width)`` of the training images, pixels.
        mean, std: per-channel normalisation of RGB values scaled to [0, 1].
        output_stride: pixels per output cell.
        training_data: description of the training data (source, size, randomisation).
        licence: licence of the weights.
        origin: who/what produced them (command, config, commit).
        metrics: evaluation metrics, name -> value.
        training: training facts (epochs, steps, wall time in seconds, hardware).
        created: ISO-8601 UTC time the record was made.
        decode: the decoding settings chosen for this network (:class:`DecodeConfig` fields
            that differ from the library's defaults, e.g. ``{"crop_blend_max_deg": 45.0}``),
            chosen on held-out renders and stated in its model card; estimators built from the
            weights use them unless given a ``decode`` of their own. ``{}``: the defaults.
    """

    arch: str
    object_name: str
    cuboid: Cuboid
    arch_kwargs: dict[str, Any] = field(default_factory=dict)
    input_size: tuple[int, int] = (480, 640)
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD
    output_stride: int = 8
    training_data: str = ""
    licence: str = "BSD-3-Clause"
    origin: str = ""
    metrics: dict[str, float] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)
    created: str = ""
    decode: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from evtrack.models.decode import DecodeConfig

        if not isinstance(self.decode, dict):
            raise ConfigError(f"record.decode must be a mapping of DecodeConfig fields, got "
                              f"{type(self.decode).__name__}")
        DecodeConfig.from_dict(self.decode, "record.decode")  # names the bad field
        if isinstance(self.cuboid, dict):
            self.cuboid = Cuboid.from_dict(self.cuboid, "record.cuboid")
        self.input_size = tuple(int(v) for v in self.input_size)  # type: ignore[assignment]
        self.mean = tuple(float(v) for v in self.mean)  # type: ignore[assignment]
        self.std = tuple(float(v) for v in self.std)  # type: ignore[assignment]
        if len(self.mean) != 3 or len(self.std) != 3 or min(self.std) <= 0:
            raise ConfigError(f"record mean/std need 3 values, std > 0: {self.mean}, {self.std}")
        if not self.created:
            self.created = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")

    def to_dict(self) -> dict[str, Any]:
        """Plain types only (safe for ``weights_only`` loading, JSON and YAML)."""
        d = asdict(self)
        d["cuboid"] = self.cuboid.to_dict()
        d["input_size"] = list(self.input_size)
        d["mean"] = list(self.mean)
        d["std"] = list(self.std)
        return json.loads(json.dumps(d))  # fails loudly on anything not plain

    @classmethod
    def from_dict(cls, data: Any, source: str = "record") -> WeightsRecord:
        if not isinstance(data, dict):
            raise WeightsError(source, f"record must be a mapping, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        missing = sorted({"arch", "object_name", "cuboid"} - set(data))
        if missing:
            raise WeightsError(source, f"record lacks field(s) {missing}")
        unknown = sorted(set(data) - known)
        if unknown:
            raise WeightsError(source, f"record has unknown field(s) {unknown}")
        try:
            return cls(**data)
        except (TypeError, ValueError) as exc:
            raise WeightsError(source, f"invalid record: {exc}") from exc


def save_weights(path: str | Path, net: torch.nn.Module, record: WeightsRecord) -> Path:
    """Write ``net``'s state dict and ``record`` atomically to ``path`` (a ``.pt`` file)."""
    return _save_state(path, net.state_dict(), record)


def set_record_decode(path: str | Path, decode: dict[str, Any], out: str | Path | None = None
                      ) -> Path:
    """Write the weights at ``path`` with ``WeightsRecord.decode`` set to ``decode`` (the
    network's chosen :class:`~evtrack.models.DecodeConfig` fields; ``{}``: the defaults) to
    ``out`` (default: ``path`` itself, replaced atomically). The state dict is copied as it is.

    Raises:
        WeightsError: ``path`` unreadable; ConfigError: a field ``DecodeConfig`` lacks or a
            value it refuses.
    """
    record, state = load_weights_file(path)
    record = replace(record, decode=dict(decode))
    return _save_state(Path(path) if out is None else out, state, record)


def _save_state(path: str | Path, state_dict: dict[str, torch.Tensor], record: WeightsRecord
                ) -> Path:
    from evtrack.utils import atomic_path

    path = Path(path)
    state = {k: v.detach().cpu().contiguous() for k, v in state_dict.items()}
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "record": record.to_dict(),
        "state_dict": state,
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


_OTHER_FORMATS = (
    (b"\x89HDF\r\n\x1a\n", "an HDF5 file", ""),
    (b"\x08", "an ONNX model", " (OnnxPoseEstimator runs it; export and set-decode take the "
                                ".pt it came from)"),
    (b"\x89PNG", "a PNG image", ""),
)
"""Leading bytes of files often given as weights by mistake: what they are, and a hint. (An
ONNX model is a protobuf whose first field, ``ir_version``, starts with the byte 0x08.)"""


def load_weights_file(path: str | Path) -> tuple[WeightsRecord, dict[str, torch.Tensor]]:
    """Read a weights file or an ``evtrack train`` Lightning checkpoint.

    Uses ``torch.load(..., weights_only=True)``: no code is unpickled.

    Returns:
        The record and the network's state dict (prefix-free).

    Raises:
        WeightsError: missing, unreadable or of an unknown layout.
    """
    path = Path(path)
    if not path.is_file():
        raise WeightsError(path, "weights file not found")
    with open(path, "rb") as fh:
        head = fh.read(8)
    known = next(((kind, hint) for magic, kind, hint in _OTHER_FORMATS
                  if head.startswith(magic)), None)
    if known is not None:
        raise WeightsError(path, f"this is {known[0]}, not a .pt weights file{known[1]}")
    if not (head.startswith(b"PK") or head.startswith(b"\x80")):
        raise WeightsError(path, "not a weights file: neither a torch.save zip archive nor a "
                                 "pickle (truncated, or another kind of file)")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for corrupt/unsafe files
        text = str(exc)
        lines = [ln.strip() for ln in text.splitlines() if "WeightsUnpickler error" in ln]
        reason = lines[0] if lines else text.strip().splitlines()[0] if text.strip() else repr(exc)
        raise WeightsError(path, f"cannot read weights (weights_only=True): {reason}") from exc
    if not isinstance(payload, dict):
        raise WeightsError(path, f"expected a dict, found {type(payload).__name__}")
    if payload.get("format") == FORMAT:
        version = payload.get("format_version")
        if version != FORMAT_VERSION:
            raise WeightsError(path, f"weights format version {version} is not supported "
                                     f"(this evtrack reads version {FORMAT_VERSION})")
        record = WeightsRecord.from_dict(payload.get("record"), f"{path}: record")
        state = payload.get("state_dict")
    elif "state_dict" in payload and "hyper_parameters" in payload:
        hparams = payload["hyper_parameters"] or {}
        if "record" not in hparams:
            raise WeightsError(path, "Lightning checkpoint without an evtrack weights record "
                                     "(not written by 'evtrack train')")
        record = WeightsRecord.from_dict(hparams["record"], f"{path}: hyper_parameters.record")
        state = {
            k[len(LIGHTNING_PREFIX):]: v
            for k, v in payload["state_dict"].items()
            if k.startswith(LIGHTNING_PREFIX)
        }
    else:
        raise WeightsError(path, "not an evtrack weights file or training checkpoint "
                                 f"(keys: {sorted(map(str, payload))[:8]})")
    if not isinstance(state, dict) or not state:
        raise WeightsError(path, "holds no network state dict")
    return record, state


def read_record(path: str | Path) -> tuple[WeightsRecord | None, str]:
    """The record and precision (``"fp32"``/``"fp16"``) of a pose network's file, whatever its
    kind: ``.onnx`` (an export: :func:`~evtrack.models.onnx_export.read_onnx_record`, whose
    record may be ``None``) or ``.pt`` weights / a Lightning checkpoint
    (:func:`load_weights_file`, always FP32).

    Raises:
        WeightsError: missing or unreadable, naming the file.
    """
    if Path(path).suffix.lower() == ".onnx":
        from evtrack.models.onnx_export import read_onnx_record

        return read_onnx_record(path)
    return load_weights_file(path)[0], "fp32"


def zoo_dir() -> Path:
    """The folder of shipped weights (``models/weights``)."""
    return Path(__file__).resolve().parent / "weights"


def list_weights(folder: str | Path | None = None) -> list[tuple[Path, WeightsRecord]]:
    """Every weights file in ``folder`` (default: the shipped zoo) with its record."""
    folder = Path(folder) if folder is not None else zoo_dir()
    if not folder.is_dir():
        return []
    return [(p, load_weights_file(p)[0]) for p in sorted(folder.glob("*.pt"))]


def find_default_weights(
    arch: str, object_name: str | None = None, folder: str | Path | None = None
) -> Path:
    """The shipped weights file for ``arch`` (and ``object_name`` if given).

    Raises:
        WeightsError: when none or several match.
    """
    entries = list_weights(folder)
    hits = [
        p for p, r in entries
        if r.arch == arch and (object_name is None or r.object_name == object_name)
    ]
    where = folder or zoo_dir()
    if not hits:
        have = ", ".join(f"{r.arch}/{r.object_name}" for _, r in entries) or "none"
        wanted = arch + (f" for object {object_name!r}" if object_name else "")
        raise WeightsError(where, f"no shipped weights for {wanted} (available: {have}); "
                                  "train some with 'evtrack train --config configs/pose_*.yaml'")
    if len(hits) > 1:
        names = ", ".join(p.name for p in hits)
        raise WeightsError(where, f"several weights for {arch} ({names}); pass object_name=...")
    return hits[0]


def model_card(record: WeightsRecord, config: dict[str, Any] | None = None) -> str:
    """A Markdown model card: what the weights are, how they were trained, how well they do."""
    kwargs = json.dumps(record.arch_kwargs) if record.arch_kwargs else "(registry defaults)"
    lines = [
        f"# {record.arch} — {record.object_name}",
        "",
        f"- Architecture: `{record.arch}` {kwargs}",
        f"- Object: `{record.object_name}`, cuboid {record.cuboid.dimensions} m "
        f"centred at {record.cuboid.center} m (mesh frame)",
        f"- Input: RGB uint8 -> [0,1] -> (x - {list(record.mean)}) / {list(record.std)}; "
        f"trained at {record.input_size[1]}x{record.input_size[0]}; output stride "
        f"{record.output_stride}",
        f"- Training data: {record.training_data or 'not stated'}",
        f"- Licence: {record.licence}",
        f"- Origin: {record.origin or 'not stated'}",
        f"- Created: {record.created}",
        f"- Decoding: {json.dumps(record.decode) if record.decode else 'the library defaults'}",
        "",
        "## Training",
        "",
    ]
    lines += [f"- {k}: {v}" for k, v in sorted(record.training.items())] or ["- not recorded"]
    lines += ["", "## Metrics", ""]
    lines += [f"- {k}: {v:.6g}" if isinstance(v, float) else f"- {k}: {v}"
              for k, v in sorted(record.metrics.items())] or ["- not measured"]
    if config is not None:
        lines += ["", "## Config", "", "```yaml", yaml.safe_dump(config, sort_keys=False).rstrip(),
                  "```"]
    return "\n".join(lines) + "\n"


def write_model_card(
    path: str | Path, record: WeightsRecord, config: dict[str, Any] | None = None
) -> Path:
    """Write :func:`model_card` atomically to ``path``."""
    from evtrack.utils import atomic_write_text

    atomic_write_text(path, model_card(record, config))
    return Path(path)
