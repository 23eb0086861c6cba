"""Training configuration: dataclasses with documented defaults, loaded from YAML (no eval).

A config file has the sections of :class:`TrainConfig`; every field not given keeps its
default, an unknown, mistyped or out-of-range field is a :class:`~evtrack.errors.ConfigError`
naming the file and the field (:mod:`evtrack.configs` reads it).
Relative paths (``object.mesh``, ``data.cache_dir``, ``output_dir``, shard folders) are
relative to the working directory, as with Lightning's CLI: run ``evtrack train`` from the
repository root. ``trainer`` is passed to ``lightning.Trainer`` unchanged (accelerator, devices,
strategy, num_nodes, precision, max_epochs, ...), which is how multi-GPU and multi-node
training are configured.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, Literal

from evtrack.configs import Config, FieldError, apply_overrides, setting
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
    "apply_overrides",
    "RESERVED_TRAINER_KEYS",
]

# Trainer arguments that evtrack train sets itself
RESERVED_TRAINER_KEYS = ("logger", "callbacks", "default_root_dir", "use_distributed_sampler")


# ---------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class ObjectConfig(Config):
    """The object to learn.

    The cuboid comes from ``mesh``, else from ``dimensions``, else from the synthetic data
    engine's object of that ``name`` (a procedural ``box``/``can``/``bottle`` or a YCB name).

    Attributes:
        name: object name (stored with the weights; estimators report it).
        mesh: mesh file (glTF, OBJ, PLY, ...); its bounding box gives the cuboid. A BOP model
            (``obj_000005.ply`` beside a ``models_info.json``) is read in millimetres.
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

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.mesh is not None and self.dimensions is not None:
            raise FieldError(self, "mesh", "give either mesh or dimensions, not both")

    def cuboid(self) -> Cuboid:
        """The object's cuboid (see the class docstring for where it comes from)."""
        if self.mesh is not None:
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
class ModelConfig(Config):
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
        super().__post_init__()
        if self.init_transfer and self.init_weights is None:
            raise FieldError(self, "init_transfer", "is set but init_weights is not: name the "
                             "weights to transfer from")


@dataclass(frozen=True)
class DataConfig(Config):
    """Training and validation data.

    Attributes:
        source: registered source kind for training samples (``cuboid``, ``shards``, ``sim``,
            ``bop``).
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
    train_samples: int = setting(4096, ge=1)
    val_samples: int = setting(256, ge=0)
    image_size: tuple[int, int] = (240, 320)
    seed: int = 0
    val_seed: int = 1
    cache_dir: str | None = None
    samples_per_shard: int = setting(256, ge=1)
    render_workers: int = setting(0, ge=0)
    batch_size: int = setting(16, ge=1)
    num_workers: int = setting(0, ge=0)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    targets: TargetConfig = field(default_factory=TargetConfig)

    def __post_init__(self) -> None:
        super().__post_init__()
        h, w = self.image_size
        if h <= 0 or w <= 0 or h % 8 or w % 8:
            raise FieldError(self, "image_size", f"must be positive multiples of 8, got "
                             f"{self.image_size}")
        if self.seed == self.val_seed and self.val_source is None and self.val_samples:
            raise ConfigError("seed and val_seed are equal, so validation samples would "
                              "repeat training samples")


_TRAINER_INTEGERS = ("max_epochs", "min_epochs", "max_steps", "min_steps", "num_nodes",
                     "log_every_n_steps", "check_val_every_n_epoch", "accumulate_grad_batches",
                     "num_sanity_val_steps")
"""``lightning.Trainer`` arguments that must be integers (Lightning itself would fail only once
the run starts, after the renders)."""
_TRAINER_NUMBERS = ("gradient_clip_val",)


@dataclass(frozen=True)
class TrainConfig(Config):
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
    logger: Literal["csv", "tensorboard"] = "csv"
    licence: str = "BSD-3-Clause"

    def __post_init__(self) -> None:
        super().__post_init__()
        reserved = sorted(set(self.trainer) & set(RESERVED_TRAINER_KEYS))
        if reserved:
            raise FieldError(self, "trainer", f"{reserved} are set by evtrack train; remove them")
        import lightning

        accepted = set(inspect.signature(lightning.Trainer.__init__).parameters) - {"self"}
        unknown = sorted(set(self.trainer) - accepted)
        if unknown:
            raise FieldError(self, "trainer", f"unknown lightning.Trainer argument(s) {unknown}")
        for key, value in self.trainer.items():  # the common numbers, before any rendering
            problem = _trainer_value_problem(key, value)
            if problem:
                raise FieldError(self, f"trainer.{key}", problem)

    @property
    def name(self) -> str:
        return self.run_name or f"{self.object.name}_{self.model.name}"


def _trainer_value_problem(key: str, value: Any) -> str | None:
    """What is wrong with the ``lightning.Trainer`` argument ``key=value`` that Lightning
    itself would find only once the run starts, or ``None``."""
    if value is None:
        return None
    if key in _TRAINER_INTEGERS and (isinstance(value, bool) or not isinstance(value, int)):
        return f"expected an integer, got {value!r}"
    if key in _TRAINER_NUMBERS and (isinstance(value, bool)
                                    or not isinstance(value, int | float)):
        return f"expected a number, got {value!r}"
    return None
