"""The ``LightningModule`` that trains a pose network on belief maps and affinity fields.

The loss is DOPE's — mean squared error between every stage's belief maps and affinity fields
and their targets, summed over stages — with one change: the squared error of each cell is
weighted by ``1 + positive_weight * target`` (belief; ``target`` in [0, 1]) and
``1 + positive_weight`` inside the affinity discs. Keypoint Gaussians cover well under 1% of the
cells, so with plain MSE a network first learns to output zeros everywhere and stays there for
thousands of steps (the all-zero output has nearly the lowest loss); weighting the positives
removes that plateau. ``positive_weight = 0`` gives DOPE's plain MSE.

Inference never needs this module: the trained network is saved as a weights file
(:func:`evtrack.models.save_weights`) and loaded with :func:`evtrack.models.create`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import lightning as L
import numpy as np
import torch
from torch import Tensor, nn

from evtrack.errors import ConfigError
from evtrack.models.keypoints import find_peaks
from evtrack.models.weights import WeightsRecord

__all__ = [
    "OptimConfig", "LossConfig", "PoseLightningModule", "corner_identity_hits",
    "corner_identity_loss",
    "keypoint_metrics", "weighted_mse",
]


@dataclass(frozen=True)
class OptimConfig:
    """AdamW with an optional cosine schedule.

    Attributes:
        lr: peak learning rate.
        weight_decay: AdamW weight decay.
        schedule: ``"cosine"`` (to ``lr * final_lr_fraction`` over the run, per step) or
            ``"constant"``.
        warmup_steps: linear warm-up steps from 0.
        final_lr_fraction: end of the cosine schedule as a fraction of ``lr``.
        schedule_by: what the cosine's progress counts: ``"steps"`` (of ``max_epochs`` or
            ``max_steps``) or ``"time"``: the larger of the step fraction and the fraction of
            ``trainer.max_time`` spent, so a run that a time budget stops still ends its
            schedule (a 2-core run that reached 28 of 44 planned epochs stopped at 64% of its
            cosine). With ``"time"`` the learning rate of a step depends on the machine's
            speed, so two runs of one config are no longer the same bit for bit.
        ema_decay: keep an exponential moving average of the weights (and of the batch-norm
            statistics), ``avg = ema_decay * avg + (1 - ema_decay) * w`` after every optimiser
            step from ``ema_start_step`` on, validate and checkpoint it, and export it
            (Lightning's :class:`~lightning.pytorch.callbacks.EMAWeightAveraging`); its horizon
            is ~``1 / (1 - ema_decay)`` steps. 0 (the default): off. Averaging smooths the
            step-to-step noise of the last weights, which on the mustard bottle's CPU
            continuations moved the median pose error by ~1 cm and ~1 deg from run to run.
        ema_start_step: the first optimiser step (0-based) that enters the average; the
            average starts as a copy of the weights after it.
    """

    lr: float = 2e-3
    weight_decay: float = 1e-4
    schedule: str = "cosine"
    warmup_steps: int = 100
    final_lr_fraction: float = 0.02
    schedule_by: str = "steps"
    ema_decay: float = 0.0
    ema_start_step: int = 0

    def __post_init__(self) -> None:
        if self.schedule not in ("cosine", "constant"):
            raise ConfigError(f"optim.schedule must be 'cosine' or 'constant', "
                              f"got {self.schedule!r}")
        if self.schedule_by not in ("steps", "time"):
            raise ConfigError(f"optim.schedule_by must be 'steps' or 'time', "
                              f"got {self.schedule_by!r}")
        if self.lr <= 0 or self.weight_decay < 0 or self.warmup_steps < 0:
            raise ConfigError("optim: lr must be > 0, weight_decay and warmup_steps >= 0")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ConfigError(f"optim.ema_decay must be in [0, 1) (0: no weight average), "
                              f"got {self.ema_decay!r}")
        if self.ema_start_step < 0:
            raise ConfigError(f"optim.ema_start_step must be >= 0, got {self.ema_start_step!r}")


@dataclass(frozen=True)
class LossConfig:
    """Loss weights.

    Attributes:
        belief_weight: weight of the belief-map MSE.
        affinity_weight: weight of the affinity-field MSE.
        positive_weight: extra weight of the cells near keypoints: a belief cell's squared error
            is weighted by ``1 + positive_weight * target``, an affinity cell's inside a
            corner's disc by ``1 + positive_weight`` (0 = plain MSE, as DOPE).
        shared_positive_weight: the belief weight of a cell is shared by the 9 maps: it weighs
            ``1 + positive_weight * max_k target_k`` (the largest target of *any* keypoint) in
            every map, so a map firing on another keypoint costs as much as missing its own.
            With per-map weights (``False``) a corner map that fires on all 8 corners pays 1 for
            each of the 7 wrong ones and gains ``1 + positive_weight`` on the right one, and the
            network learns where corners are long before it learns which corner is which.
            Affinity weights stay per corner either way (sharing them drives every affinity
            field towards zero wherever the network is unsure which corner it sees, and the
            decoder then cannot group corners into instances). Off by default: in a 38-minute
            CPU run on the demo box it reached half the validation recall of per-map weights.
        identity_weight: weight of the corner-identity term: at every cell within the core of a
            corner's Gaussian (target >= ``identity_min_target``) the 8 corner maps, times
            ``identity_temperature``, are read as logits of *which* corner is there and scored by
            cross-entropy against the nearest corner. The MSE alone pays little for a corner map
            that also fires on the other 7 corners (see ``shared_positive_weight``); this term
            pays for exactly that confusion, and leaves the maps' values to the MSE elsewhere.
            0 = off (DOPE's loss). Tried at 0.05 on the demo box (10 epochs, 1,919 steps on 2
            CPU cores): the term stayed at chance (2.10 nats; ln 8 = 2.08) and the validation
            recall matched a run without it (0.091 against 0.100): within a CPU budget the
            network does not yet separate the corners, whatever the loss says.
        identity_temperature: scale from belief values (0..1) to logits.
        identity_min_target: cells whose largest corner target is below this are not scored.
        last_stage_weight: weight of the last stage (earlier stages weigh 1).
        match_px: a predicted peak within this distance of a true keypoint counts as found
            (validation metrics).
        peak_threshold: minimum belief value of a peak (validation metrics).
    """

    belief_weight: float = 1.0
    affinity_weight: float = 1.0
    positive_weight: float = 20.0
    shared_positive_weight: bool = False
    identity_weight: float = 0.0
    identity_temperature: float = 10.0
    identity_min_target: float = 0.5
    last_stage_weight: float = 1.0
    match_px: float = 8.0
    peak_threshold: float = 0.1

    def __post_init__(self) -> None:
        if min(self.belief_weight, self.affinity_weight, self.positive_weight,
               self.last_stage_weight, self.identity_weight) < 0:
            raise ConfigError(f"loss: weights must be >= 0, got {self}")
        if self.identity_temperature <= 0 or not 0 < self.identity_min_target <= 1:
            raise ConfigError("loss: identity_temperature must be > 0 and identity_min_target "
                              f"in (0, 1], got {self.identity_temperature}, "
                              f"{self.identity_min_target}")


def weighted_mse(pred: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """Mean over all elements of ``weight * (pred - target)**2`` (weight broadcasts)."""
    return (weight * (pred - target).square()).mean()


def corner_identity_loss(pred: Tensor, target: Tensor, temperature: float,
                         min_target: float) -> Tensor:
    """Cross-entropy of *which* corner each corner cell shows, read from the 8 corner maps.

    Args:
        pred: (B, 9, h, w) predicted belief maps (channel 8, the centroid, is not used).
        target: (B, 9, h, w) target belief maps.
        temperature: logits are ``temperature * pred[:, :8]``.
        min_target: cells whose largest corner target is below this are not scored.

    Returns:
        Scalar mean cross-entropy over the scored cells (0 when there are none), nats.
    """
    corner_target = target[:, :8]
    peak, label = corner_target.max(dim=1)                      # (B, h, w)
    scored = peak >= min_target
    if not bool(scored.any()):
        return pred.new_zeros(())
    logits = (temperature * pred[:, :8]).movedim(1, -1)[scored]  # (N, 8)
    return nn.functional.cross_entropy(logits, label[scored])


def corner_identity_hits(pred: Tensor, target: Tensor) -> tuple[int, int]:
    """How often the right corner map is the strongest at a corner's own peak cell.

    At the cell where each corner's target Gaussian peaks (a target of at least 0.99: the
    cell nearest the corner), the 8 predicted corner maps are compared; a hit is the right map
    being the largest. Chance is 1/8. This isolates *which* corner the network sees from
    *where* corners are (what :func:`keypoint_metrics` mixes): a network that fires on every
    corner scores well on localisation and at chance here.

    Args:
        pred, target: (B, 9, h, w) belief maps.

    Returns:
        ``(hits, cells)``.
    """
    corner_target = target[:, :8]
    peak_value, label = corner_target.max(dim=1)
    cells = peak_value >= 0.99
    if not bool(cells.any()):
        return 0, 0
    guess = pred[:, :8].argmax(dim=1)
    return int((guess[cells] == label[cells]).sum()), int(cells.sum())


def keypoint_metrics(
    pred_belief: np.ndarray, target_belief: np.ndarray, stride: int, threshold: float,
    match_px: float,
) -> tuple[int, int, list[float]]:
    """Compare predicted and target keypoint peaks of a batch.

    Target peaks are the keypoints' Gaussians. With one target peak in a channel (one object
    instance), it is matched to the channel's *strongest* predicted peak — the one a
    single-instance decoder uses — so a network that puts a peak on every corner without
    knowing which corner is which does not score; with several instances, each target peak is
    matched to the nearest predicted peak of the channel.

    Args:
        pred_belief, target_belief: (B, 9, h, w).

    Returns:
        ``(found, total, errors_px)``: target keypoints with a predicted peak within
        ``match_px``, all target keypoints, and the pixel errors of the found ones.
    """
    found, total, errors = 0, 0, []
    for pred, target in zip(pred_belief, target_belief, strict=True):
        pp = find_peaks(pred, threshold)
        tp = find_peaks(target, 0.5)
        for c in range(len(tp)):
            for x, y, _ in tp[c]:
                total += 1
                if len(pp[c]) == 0:
                    continue
                cand = pp[c]
                if len(tp[c]) == 1:
                    cand = cand[np.argmax(cand[:, 2])][None]
                d = np.hypot(cand[:, 0] - x, cand[:, 1] - y).min() * stride
                if d <= match_px:
                    found += 1
                    errors.append(float(d))
    return found, total, errors


class PoseLightningModule(L.LightningModule):
    """Trains a pose network (``net``) on batches of images, belief and affinity targets.

    Args:
        net: a network from :func:`evtrack.models.create` (it carries ``arch_name`` and
            ``arch_kwargs``); its ``forward_stages`` gives every stage's maps.
        record: the weights record to save with the weights (object, cuboid, normalisation).
        optim: optimiser settings.
        loss: loss weights.
        channels_last: run the network and its inputs in the NHWC memory format (faster
            training on CPUs with oneDNN; the weights are the same).

    The hyper-parameters saved in checkpoints are plain dicts (record, optim, loss), so
    checkpoints load with ``torch.load(..., weights_only=True)`` and
    :func:`evtrack.models.create` reads them directly.
    """

    def __init__(
        self,
        net: nn.Module,
        record: WeightsRecord,
        optim: OptimConfig | None = None,
        loss: LossConfig | None = None,
        *,
        channels_last: bool = False,
    ) -> None:
        super().__init__()
        arch = getattr(net, "arch_name", None)
        if arch is None:
            raise ConfigError("net must come from evtrack.models.create (it has no arch_name)")
        if record.arch != arch or record.arch_kwargs != getattr(net, "arch_kwargs", {}):
            raise ConfigError(f"record describes {record.arch} {record.arch_kwargs}, the net is "
                              f"{arch} {net.arch_kwargs}")
        self.channels_last = bool(channels_last)
        self.net = net.to(memory_format=torch.channels_last) if channels_last else net
        self.record = record
        self.optim_config = optim or OptimConfig()
        self.loss_config = loss or LossConfig()
        self.save_hyperparameters({
            "record": record.to_dict(),
            "optim": asdict(self.optim_config),
            "loss": asdict(self.loss_config),
        })
        self._val_found = self._val_total = 0
        self._val_errors: list[float] = []
        self._val_id_hits = self._val_id_cells = 0

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return self.net(x)

    def compute_loss(
        self, stages: list[tuple[Tensor, Tensor]], belief: Tensor, affinity: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Weighted sum over stages of the loss terms: (total, belief, affinity, identity).

        ``identity`` is the corner-identity cross-entropy (:func:`corner_identity_loss`),
        zero unless ``identity_weight > 0``.

        Args:
            stages: every stage's ``(belief (B,9,h,w), affinity (B,16,h,w))``.
            belief, affinity: targets of the same shapes.
        """
        cfg = self.loss_config
        # affinity discs: cells where a corner's (dx, dy) target is set
        disc = (affinity.unflatten(1, (-1, 2)).abs().sum(2) > 0).repeat_interleave(2, dim=1)
        if cfg.shared_positive_weight:
            w_belief = 1.0 + cfg.positive_weight * belief.amax(dim=1, keepdim=True)
        else:
            w_belief = 1.0 + cfg.positive_weight * belief
        w_affinity = 1.0 + cfg.positive_weight * disc.to(affinity.dtype)
        lb = belief.new_zeros(())
        la = belief.new_zeros(())
        li = belief.new_zeros(())
        for i, (b, a) in enumerate(stages):
            w = cfg.last_stage_weight if i == len(stages) - 1 else 1.0
            lb = lb + w * weighted_mse(b, belief, w_belief)
            la = la + w * weighted_mse(a, affinity, w_affinity)
            if cfg.identity_weight > 0:
                li = li + w * corner_identity_loss(b, belief, cfg.identity_temperature,
                                                   cfg.identity_min_target)
        total = cfg.belief_weight * lb + cfg.affinity_weight * la + cfg.identity_weight * li
        return total, lb, la, li

    def _common_step(self, batch: dict[str, Tensor], stage: str) -> Tensor:
        image = batch["image"]
        if self.channels_last:
            image = image.contiguous(memory_format=torch.channels_last)
        stages = self.net.forward_stages(image)
        loss, lb, la, li = self.compute_loss(stages, batch["belief"], batch["affinity"])
        bs = batch["image"].shape[0]
        train = stage == "train"
        self.log(f"{stage}/loss", loss, prog_bar=True, on_step=train, on_epoch=True,
                 batch_size=bs, sync_dist=not train)
        self.log(f"{stage}/loss_belief", lb, on_step=False, on_epoch=True, batch_size=bs,
                 sync_dist=not train)
        self.log(f"{stage}/loss_affinity", la, on_step=False, on_epoch=True, batch_size=bs,
                 sync_dist=not train)
        if self.loss_config.identity_weight > 0:
            self.log(f"{stage}/loss_identity", li, on_step=False, on_epoch=True,
                     batch_size=bs, sync_dist=not train)
        if not train:
            found, total, errors = keypoint_metrics(
                stages[-1][0].detach().float().cpu().numpy(), batch["belief"].cpu().numpy(),
                self.record.output_stride, self.loss_config.peak_threshold,
                self.loss_config.match_px,
            )
            self._val_found += found
            self._val_total += total
            self._val_errors += errors
            hits, cells = corner_identity_hits(stages[-1][0].detach(), batch["belief"])
            self._val_id_hits += hits
            self._val_id_cells += cells
        return loss

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        return self._common_step(batch, "train")

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        return self._common_step(batch, "val")

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        return self._common_step(batch, "test")

    def _log_keypoint_metrics(self, stage: str) -> None:
        recall = self._val_found / self._val_total if self._val_total else 0.0
        median = float(np.median(self._val_errors)) if self._val_errors else float("nan")
        self.log(f"{stage}/keypoint_recall", recall, sync_dist=True)
        self.log(f"{stage}/keypoint_error_px", median, sync_dist=True)
        identity = self._val_id_hits / self._val_id_cells if self._val_id_cells else 0.0
        self.log(f"{stage}/corner_identity", identity, sync_dist=True)
        self._val_found = self._val_total = 0
        self._val_errors = []
        self._val_id_hits = self._val_id_cells = 0

    def on_validation_epoch_end(self) -> None:
        self._log_keypoint_metrics("val")

    def on_test_epoch_end(self) -> None:
        self._log_keypoint_metrics("test")

    def configure_optimizers(self):
        cfg = self.optim_config
        opt = torch.optim.AdamW(self.net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        total = max(1, int(self.trainer.estimated_stepping_batches)) if self._trainer else 1
        warm = min(cfg.warmup_steps, max(0, total - 1))
        timer = self._schedule_timer() if cfg.schedule_by == "time" else None

        def factor(step: int) -> float:
            if step < warm:
                return (step + 1) / (warm + 1)
            if cfg.schedule == "constant":
                return 1.0
            progress = min(1.0, (step - warm) / max(1, total - warm))
            if timer is not None:
                elapsed, remaining = timer.time_elapsed(), timer.time_remaining()
                if remaining is not None and elapsed + remaining > 0:
                    progress = max(progress, min(1.0, elapsed / (elapsed + remaining)))
            lo = cfg.final_lr_fraction
            # a Python float: numpy scalars would make checkpoints unloadable with weights_only
            return float(lo + (1 - lo) * 0.5 * (1 + math.cos(math.pi * progress)))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def _schedule_timer(self):
        """The trainer's ``max_time`` timer, which ``optim.schedule_by: time`` follows."""
        from lightning.pytorch.callbacks import Timer

        timers = [c for c in (self.trainer.callbacks if self._trainer else [])
                  if isinstance(c, Timer)]
        if not timers:
            raise ConfigError("optim.schedule_by: 'time' needs trainer.max_time (the time "
                              "budget the schedule spreads over)")
        return timers[0]

    def export_weights(self, path: str, **record_updates) -> str:
        """Save the network with its record (updated with ``record_updates``) as a weights file."""
        from dataclasses import replace

        from evtrack.models.weights import save_weights

        record = replace(self.record, **record_updates) if record_updates else self.record
        save_weights(path, self.net, record)
        return path
