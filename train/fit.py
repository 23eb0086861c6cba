"""``run_training(config)``: the whole ``evtrack train`` job.

Writes, under ``output_dir/run_name/``:

* ``config.yaml``: the resolved config,
* ``checkpoints/last.ckpt`` (the latest state, :class:`LastCheckpoint`) and
  ``checkpoints/best-*.ckpt`` (the lowest validation loss; Lightning; both resumable),
* ``logs/version_N/metrics.csv`` (or TensorBoard events),
* ``<object>_<model>.pt``: the best network as a weights file (``evtrack.models.create``
  loads it) and ``<object>_<model>.md``, its model card (config, data, time, metrics).
"""

from __future__ import annotations

import platform
import time
from dataclasses import dataclass, replace
from pathlib import Path

import lightning as L
import numpy as np
import torch
import yaml

from evtrack.errors import ConfigError
from evtrack.models.factory import create
from evtrack.models.weights import (
    WeightsError,
    WeightsRecord,
    load_weights_file,
    write_model_card,
)
from evtrack.train.config import TrainConfig
from evtrack.train.data import PoseDataModule
from evtrack.train.module import OptimConfig, PoseLightningModule
from evtrack.utils import atomic_write_text

__all__ = ["TrainResult", "run_training", "build_module", "resolve_resume", "weight_averaging",
           "LastCheckpoint"]


@dataclass
class TrainResult:
    """Where a run wrote its outputs, and its final metrics."""

    run_dir: Path
    weights: Path | None
    card: Path | None
    best_checkpoint: Path | None
    last_checkpoint: Path | None
    metrics: dict[str, float]
    wall_time_s: float


def build_module(config: TrainConfig) -> tuple[PoseLightningModule, PoseDataModule]:
    """The Lightning module (fresh network) and data module a config describes."""
    cuboid = config.object.cuboid()
    if config.model.init_weights is not None:
        net = _initial_network(config)
    else:
        net = create(config.model.name, **config.model.kwargs)
    record = WeightsRecord(
        arch=config.model.name, arch_kwargs=dict(config.model.kwargs),
        object_name=config.object.name, cuboid=cuboid, input_size=tuple(config.data.image_size),
        mean=config.model.mean, std=config.model.std,
        output_stride=int(net.output_stride), licence=config.licence,
        origin=f"evtrack train (run {config.name})",
    )
    if config.data.targets.stride != record.output_stride:
        raise ConfigError(f"data.targets.stride {config.data.targets.stride} differs from the "
                          f"network's output stride {record.output_stride}")
    module = PoseLightningModule(net, record, config.optim, config.loss,
                                 channels_last=config.model.channels_last)
    data = PoseDataModule(config.data, config.object.name, cuboid, config.object.mesh,
                          config.model.mean, config.model.std)
    return module, data


def _initial_network(config: TrainConfig):
    """The network loaded from ``model.init_weights``, checked against the config, in train
    mode (:func:`evtrack.models.create` refuses another architecture, object or
    hyper-parameters; the record's input normalisation must match too). With
    ``model.init_transfer`` the weights may come from another object."""
    path = Path(config.model.init_weights)
    if not path.is_file():
        raise ConfigError(f"model.init_weights: {path} not found")
    object_name = None if config.model.init_transfer else config.object.name
    net = create(config.model.name, weights=path, object_name=object_name,
                 **config.model.kwargs)
    record, _ = load_weights_file(path)
    if (not np.allclose(record.mean, config.model.mean)
            or not np.allclose(record.std, config.model.std)):
        raise WeightsError(path, f"was trained with input mean/std {record.mean}/{record.std}, "
                                 f"the config has {config.model.mean}/{config.model.std}")
    return net.train()


class LastCheckpoint(L.Callback):
    """Keeps ``path`` (``checkpoints/last.ckpt``) the run's latest state: written at the end
    of a training epoch when ``every_s`` seconds have passed since the last write, and when
    training ends (a ``max_time`` or ``max_steps`` stop included), through a temporary file
    and a rename, so an interrupted write leaves the previous one.

    Lightning's ``ModelCheckpoint(save_last=True)`` writes ``last.ckpt`` only when it also
    writes a top-k checkpoint: once the monitored loss stops improving, its "last" stays at the
    best epoch, ``--resume auto`` went back there, and the end of the run (with
    ``optim.ema_decay``, its final average) was never written (a 75-minute run's last was at
    step 1280 of 5011). Place it before a weight-averaging callback: at the end of training
    it then saves the raw weights with the average before the average replaces them.
    """

    def __init__(self, path: Path, every_s: float = 60.0) -> None:
        self.path = Path(path)
        self.every_s = float(every_s)
        self._saved_at = time.monotonic()

    def _save(self, trainer: L.Trainer) -> None:
        if trainer.fast_dev_run:
            return
        tmp = self.path.with_name(self.path.name + ".tmp")
        # the full state (optimizer, loops, callbacks) for --resume; every rank takes part,
        # global rank 0 writes (weights_only given: Lightning logs a line per save without it)
        trainer.save_checkpoint(tmp, weights_only=False)
        if trainer.is_global_zero:
            tmp.replace(self.path)
        self._saved_at = time.monotonic()

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if time.monotonic() - self._saved_at >= self.every_s:
            self._save(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._save(trainer)


def weight_averaging(optim: OptimConfig) -> L.Callback | None:
    """The callback that averages the weights as ``optim.ema_decay`` asks, or ``None``.

    With it, validation runs on the average, checkpoints hold the average as their
    ``state_dict`` (the raw weights under ``current_model_state``, so ``--resume`` goes on from
    both) and the exported weights file is the average.
    """
    if optim.ema_decay <= 0:
        return None
    from lightning.pytorch.callbacks import EMAWeightAveraging

    return EMAWeightAveraging(decay=optim.ema_decay,
                              update_starting_at_step=optim.ema_start_step)


def resolve_resume(resume: str | None, run_dir: Path) -> str | None:
    """``None`` | ``"auto"`` (the run's last.ckpt if it exists) | a checkpoint path."""
    if resume is None:
        return None
    if resume == "auto":
        last = run_dir / "checkpoints" / "last.ckpt"
        return str(last) if last.is_file() else None
    if not Path(resume).is_file():
        raise ConfigError(f"--resume: checkpoint {resume} not found")
    return resume


def _logger(config: TrainConfig, run_dir: Path):
    from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

    if config.logger == "tensorboard":
        try:
            import tensorboard  # noqa: F401
        except ImportError as exc:
            raise ConfigError("logger: 'tensorboard' needs the tensorboard package "
                              "(pip install tensorboard), or use 'csv'") from exc
        return TensorBoardLogger(run_dir, name="logs")
    return CSVLogger(run_dir, name="logs")


def run_training(
    config: TrainConfig, *, resume: str | None = None, fast_dev_run: bool = False,
    verbose: bool = True,
) -> TrainResult:
    """Train, checkpoint, and save the best network as a weights file with a model card.

    Args:
        config: the run.
        resume: ``None``, ``"auto"`` or a checkpoint path (see :func:`resolve_resume`).
        fast_dev_run: one batch of training and validation (a smoke test of the config).
        verbose: show Lightning's progress bar and model summary.
    """
    from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint

    start = time.time()
    L.seed_everything(config.seed, workers=True, verbose=False)
    run_dir = Path(config.output_dir) / config.name
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(run_dir / "config.yaml", yaml.safe_dump(config.to_dict(), sort_keys=False))
    module, data = build_module(config)
    has_val = config.data.val_samples > 0
    checkpoint = ModelCheckpoint(
        dirpath=run_dir / "checkpoints", filename="best-{epoch:03d}",
        monitor="val/loss" if has_val else "train/loss_epoch", mode="min",
        save_top_k=1, save_last=False,
    )
    last_path = run_dir / "checkpoints" / "last.ckpt"
    callbacks = [checkpoint, LearningRateMonitor(logging_interval="step"),
                 LastCheckpoint(last_path)]
    averaging = weight_averaging(config.optim)
    if averaging is not None:
        callbacks.append(averaging)
    trainer_kwargs = {"log_every_n_steps": 10, **config.trainer}
    trainer = L.Trainer(
        **trainer_kwargs, logger=_logger(config, run_dir), callbacks=callbacks,
        default_root_dir=run_dir, use_distributed_sampler=False, fast_dev_run=fast_dev_run,
        enable_progress_bar=verbose, enable_model_summary=verbose,
    )
    trainer.fit(module, datamodule=data, ckpt_path=resolve_resume(resume, run_dir))
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
    wall = time.time() - start
    result = TrainResult(run_dir, None, None, None, None, metrics, wall)
    if fast_dev_run or not trainer.is_global_zero:
        return result
    best = Path(checkpoint.best_model_path) if checkpoint.best_model_path else None
    last = last_path if last_path.is_file() else None
    source = best or last
    if source is None:
        raise ConfigError("training produced no checkpoint (check trainer.enable_checkpointing)")
    record, state = load_weights_file(source)
    module.net.load_state_dict(state)
    record = replace(
        record,
        training_data=data.describe(),
        metrics={k: v for k, v in metrics.items() if k.startswith("val/")},
        training={
            "epochs": int(trainer.current_epoch), "steps": int(trainer.global_step),
            "wall_time_s": round(wall, 1), "checkpoint": source.name,
            "hardware": f"{platform.processor() or platform.machine()}, "
                        f"{torch.get_num_threads()} torch threads, accelerator "
                        f"{type(trainer.accelerator).__name__}, devices {trainer.num_devices}",
            "torch": torch.__version__, "lightning": L.__version__,
        },
    )
    module.record = record
    stem = f"{config.object.name}_{config.model.name}"
    weights = Path(module.export_weights(str(run_dir / f"{stem}.pt")))
    card = write_model_card(run_dir / f"{stem}.md", record, config.to_dict())
    return replace(result, weights=weights, card=card, best_checkpoint=best,
                   last_checkpoint=last)
