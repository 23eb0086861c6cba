"""Training configuration: dataclasses with documented defaults, loaded from YAML (no eval).

A config file has the sections of :class:`TrainConfig`; every field not given keeps its
default, an unknown or mistyped field is a :class:`~evtrack.errors.ConfigError` naming it.
Relative paths (``object.mesh``, ``data.cache_dir``, ``output_dir``, shard folders) are
relative to the working directory, as with Lightning's CLI: run ``evtrack train`` from the
repository root. ``trainer`` is passed to ``lightning.Trainer`` unchanged (accelerator, devices,
strategy, num_nodes, precision, max_epochs, ...), which is how multi-GPU and multi-node
training are configured.
"""

from __future__ import annotations

import dataclasses
import inspect
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from evtrack.config_values import number_from_text
from evtrack.errors import ConfigError
from evtrack.models.cuboid import Cuboid
from evtrack.models.weights import IMAGENET_MEAN, IMAGENET_STD
from evtrack.train.augment import AugmentConfig
from evtrack.train.module import LossConfig, OptimConfig
from evtrack.train.targets import TargetConfig

__all__ = [
    "ObjectConfig",
    "ModelConfig",
    "DataConfig",
    "TrainConfig",
    "load_dataclass",
    "apply_overrides",
    "RESERVED_TRAINER_KEYS",
]

# Trainer arguments that evtrack train sets itself
RESERVED_TRAINER_KEYS = ("logger", "callbacks", "default_root_dir", "use_distributed_sampler")


# ---------------------------------------------------------------------------- generic loader
def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None:
            if type(None) in args:
                return None
            raise ConfigError(f"{where}: must not be null")
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{where}: invalid value {value!r}")
    if dataclasses.is_dataclass(tp):
        if hasattr(tp, "from_dict"):
            return tp.from_dict(value, where)
        return load_dataclass(tp, value, where)
    if origin is tuple:
        if not isinstance(value, Sequence) or isinstance(value, str):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
        pairs = enumerate(zip(args, value, strict=True))
        return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in pairs)
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if tp is int:
        value = number_from_text(value)  # "1e3": YAML 1.1 reads it as a string
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        value = number_from_text(value)  # "1e-3": YAML 1.1 reads it as a string
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported field type {tp!r}")


def load_dataclass(cls: type, data: Any, where: str) -> Any:
    """Build dataclass ``cls`` from a mapping, recursively, with errors naming the field.

    Raises:
        ConfigError: not a mapping, unknown or missing fields, wrong types, invalid values.
    """
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {unknown}; known: {sorted(known)}")
    missing = [
        n for n, f in known.items()
        if n not in data and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise ConfigError(f"{where}: missing required field(s) {missing}")
    kwargs = {k: _convert(hints[k], v, f"{where}.{k}") for k, v in data.items()}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def _plain(obj: Any) -> Any:
    """Dataclasses/tuples -> dicts/lists (YAML- and JSON-safe)."""
    if hasattr(obj, "to_dict"):
        return _plain(obj.to_dict())
    if dataclasses.is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    return obj


def apply_overrides(data: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Apply ``"a.b.c=value"`` overrides (value parsed as YAML) to a nested dict copy."""
    import copy

    out = copy.deepcopy(data)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.field=value")
        key, raw = item.split("=", 1)
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"override {item!r}: empty field name")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {item!r}: value is not valid YAML: {exc}") from exc
        node = out
        for p in parts[:-1]:
            child = node.setdefault(p, {})
            if not isinstance(child, dict):
                raise ConfigError(f"override {item!r}: {p!r} is not a section")
            node = child
        node[parts[-1]] = value
    return out


# ---------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class ObjectConfig:
    """The object to learn.

    The cuboid comes from ``mesh``, else from ``dimensions``, else from the synthetic data
    engine's object of that ``name`` (a procedural ``box``/``can``/``bottle`` or a YCB name).

    Attributes:
        name: object name (stored with the weights; estimators report it).
        mesh: mesh file (glTF, OBJ, PLY, ...); its bounding box gives the cuboid.
        recenter: with a mesh, the object frame is the mesh's bounding-box-centred frame (the
            synthetic data engine's convention; poses are reported in it); ``false`` keeps
            the file's origin.
        dimensions: cuboid dimensions in metres, when there is no mesh.
        center: cuboid centre in the object frame, metres (with ``dimensions``).
    """

    name: str
    mesh: str | None = None
    recenter: bool = True
    dimensions: tuple[float, float, float] | None = None
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def cuboid(self) -> Cuboid:
        if self.mesh is not None:
            if self.dimensions is not None:
                raise ConfigError("object: give either mesh or dimensions, not both")
            box = Cuboid.from_mesh(self.mesh)
            return Cuboid(box.dimensions) if self.recenter else box
        if self.dimensions is not None:
            return Cuboid(self.dimensions, self.center)
        try:
            from evtrack.train.sim_source import sim_object_cuboid

            return sim_object_cuboid(self.name)
        except ImportError as exc:
            raise ConfigError(f"object {self.name!r}: no mesh or dimensions given, and the "
                              f"synthetic data engine is unavailable ({exc})") from exc
        except ConfigError as exc:
            raise ConfigError(f"object: needs a mesh or cuboid dimensions, or the name of an "
                              f"engine object ({exc})") from exc


@dataclass(frozen=True)
class ModelConfig:
    """The network.

    Attributes:
        name: registered model (``evtrack.models.list_models()``).
        kwargs: hyper-parameter overrides for its entry point.
        mean, std: input normalisation of RGB in [0, 1] (stored in the weights record).
        init_weights: start from these weights (a weights file or an ``evtrack train``
            checkpoint of the same architecture and object) instead of a random
            initialisation: fine-tuning, or more epochs with a fresh schedule. Unlike
            ``--resume``, the optimiser, schedule and epoch count start afresh.
        init_transfer: with ``init_weights``, accept weights trained on another object
            (transfer learning: the belief and affinity maps are cuboid-generic, so a
            network that already finds one object's cuboid corners starts closer than a
            random one). Only the tensors are taken; the object, cuboid and weights record
            come from this config. The architecture, hyper-parameters and input
            normalisation must still match.
        channels_last: train in the NHWC memory format (``torch.channels_last``). On 2 CPU
            cores (oneDNN) a ``dope_lite_small`` step with the data prepared in the training
            process took 355 / 323 ms instead of 395 / 411 ms (1.11x / 1.27x, two runs of
            ``benchmarks/bench_train_speed.py``); about as fast as NCHW with the data in one
            loader process (372 / 330 ms). The saved weights are the same either way.
    """

    name: str = "dope_lite_base"
    kwargs: dict[str, Any] = field(default_factory=dict)
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD
    init_weights: str | None = None
    init_transfer: bool = False
    channels_last: bool = False

    def __post_init__(self) -> None:
        if self.init_transfer and self.init_weights is None:
            raise ConfigError("model.init_transfer is set but model.init_weights is not: "
                              "name the weights to transfer from")


@dataclass(frozen=True)
class DataConfig:
    """Training and validation data.

    Attributes:
        source: registered source kind for training samples (``cuboid``, ``shards``, ``sim``).
        options: that source's options.
        val_source, val_options: the validation source (default: the same as training).
        train_samples, val_samples: samples per epoch / in the validation set.
        image_size: ``(height, width)``, multiples of 8.
        seed, val_seed: seeds of the training and validation samples (keep them different).
        cache_dir: when set, samples are rendered once into HDF5 shards under
            ``cache_dir/<fingerprint>/`` and read from there (else made on the fly).
        samples_per_shard: samples per shard file.
        render_workers: processes that render the shard cache (``0``: the main process);
            the shards are the same for any number.
        batch_size: per device.
        num_workers: DataLoader worker processes.
        augment: domain randomisation of training images.
        targets: belief / affinity target shape.
    """

    source: str = "cuboid"
    options: dict[str, Any] = field(default_factory=dict)
    val_source: str | None = None
    val_options: dict[str, Any] | None = None
    train_samples: int = 4096
    val_samples: int = 256
    image_size: tuple[int, int] = (240, 320)
    seed: int = 0
    val_seed: int = 1
    cache_dir: str | None = None
    samples_per_shard: int = 256
    render_workers: int = 0
    batch_size: int = 16
    num_workers: int = 0
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    targets: TargetConfig = field(default_factory=TargetConfig)

    def __post_init__(self) -> None:
        h, w = self.image_size
        if h <= 0 or w <= 0 or h % 8 or w % 8:
            raise ConfigError(f"data.image_size must be positive multiples of 8, got "
                              f"{self.image_size}")
        if self.train_samples < 1 or self.val_samples < 0 or self.batch_size < 1:
            raise ConfigError("data: train_samples and batch_size must be >= 1, "
                              "val_samples >= 0")
        if self.num_workers < 0 or self.render_workers < 0 or self.samples_per_shard < 1:
            raise ConfigError("data: num_workers and render_workers must be >= 0, "
                              "samples_per_shard >= 1")
        if self.seed == self.val_seed and self.val_source is None and self.val_samples:
            raise ConfigError("data: seed and val_seed are equal, so validation samples would "
                              "repeat training samples")


_TRAINER_INTEGERS = ("max_epochs", "min_epochs", "max_steps", "min_steps", "num_nodes",
                     "log_every_n_steps", "check_val_every_n_epoch", "accumulate_grad_batches",
                     "num_sanity_val_steps")
"""``lightning.Trainer`` arguments that must be integers (Lightning itself would fail only once
the run starts, after the renders)."""
_TRAINER_NUMBERS = ("gradient_clip_val",)


@dataclass(frozen=True)
class TrainConfig:
    """A whole training run (see the module docstring).

    Attributes:
        object: what to learn.
        model: which network.
        data: training and validation data.
        optim: optimiser and schedule.
        loss: loss weights.
        trainer: keyword arguments of ``lightning.Trainer`` (not logger/callbacks/
            default_root_dir/use_distributed_sampler, which evtrack sets).
        output_dir: runs are written to ``output_dir/run_name/``.
        run_name: default ``<object>_<model>``.
        seed: global seed (weights initialisation, data order).
        logger: ``"csv"`` or ``"tensorboard"`` (needs the tensorboard package).
        licence: licence written into the weights record.
    """

    object: ObjectConfig
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    trainer: dict[str, Any] = field(default_factory=lambda: {"max_epochs": 20})
    output_dir: str = "runs/pose"
    run_name: str | None = None
    seed: int = 0
    logger: str = "csv"
    licence: str = "BSD-3-Clause"

    def __post_init__(self) -> None:
        if self.logger not in ("csv", "tensorboard"):
            raise ConfigError(f"logger must be 'csv' or 'tensorboard', got {self.logger!r}")
        reserved = sorted(set(self.trainer) & set(RESERVED_TRAINER_KEYS))
        if reserved:
            raise ConfigError(f"trainer: {reserved} are set by evtrack train; remove them")
        import lightning

        accepted = set(inspect.signature(lightning.Trainer.__init__).parameters) - {"self"}
        unknown = sorted(set(self.trainer) - accepted)
        if unknown:
            raise ConfigError(f"trainer: unknown lightning.Trainer argument(s) {unknown}")
        for key, value in self.trainer.items():  # the common numbers, before any rendering
            if key in _TRAINER_INTEGERS and value is not None and (
                    isinstance(value, bool) or not isinstance(value, int)):
                raise ConfigError(f"trainer.{key}: expected an integer, got {value!r}")
            if key in _TRAINER_NUMBERS and value is not None and (
                    isinstance(value, bool) or not isinstance(value, int | float)):
                raise ConfigError(f"trainer.{key}: expected a number, got {value!r}")

    @property
    def name(self) -> str:
        return self.run_name or f"{self.object.name}_{self.model.name}"

    @classmethod
    def from_dict(cls, data: Any, source: str = "config") -> TrainConfig:
        return load_dataclass(cls, data, source)

    @classmethod
    def from_yaml(cls, path: str | Path, overrides: Sequence[str] = ()) -> TrainConfig:
        """Load ``path`` and apply ``section.field=value`` overrides."""
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: config file not found")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: invalid YAML: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: the top level must be a mapping of sections")
        return load_dataclass(cls, apply_overrides(data, overrides), str(path))

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (round-trips through :meth:`from_dict`)."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}
