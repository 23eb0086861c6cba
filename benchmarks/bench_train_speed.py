"""Training throughput of a pose-network config on this machine: loader settings side by side.

Runs the real training loop (``evtrack.train``: the config's data module, augmentation,
targets, Lightning module and optimiser) for a fixed number of steps per variant, in one
process, and prints the time per step after a warm-up. The variants differ only in how the
batches are made and laid out:

* ``worker+nchw``: one DataLoader worker process, contiguous (NCHW) tensors: the settings of
  the configs before the CPU recipe (``configs/pose_demo_coded_box.yaml``);
* ``main+nchw``: batches made in the training process (``data.num_workers: 0``);
* ``main+nhwc``: the same with ``model.channels_last: true`` (the CPU recipe,
  ``configs/pose_demo_coded_box_cpu*.yaml``);
* ``worker+nhwc``: one loader process and channels-last.

On 2 cores a worker process competes with the network's two threads for the cores. Measured
on 2 CPU cores (2026-11-25, two runs, ms per step): worker+nchw 372 / 330, main+nchw 395 /
411, main+nhwc 355 / 323: NHWC pays for keeping the data in the training process, no more. On
2 cores of an AMD EPYC that trains ~1.9x as fast (2026-11-27, 40 steps): stage 1's 160x160
crops, main+nhwc 149.5 / 152.2 and worker+nhwc 118.7 / 125.9 ms with 1 / 2 torch threads (the
worker 1.21-1.26x as fast: a step's network alone takes ~65 ms on 2 threads, the data ~70 ms
on one); stage 2's 256x256 crops from 640x480 renders (30 steps), main+nhwc 293.7 and
worker+nhwc 294.9 with 2 threads, 349.8 and 287.0 with 1: the network is the bound there. So
``--set data.num_workers=1`` speeds up stage 1 on such a machine; the configs keep 0, with
which their model cards were measured.
The samples are rendered once into a small cache (``--cache``); validation and checkpoints
are off, so the numbers are the training step alone. Issue 6's target is the whole recipe
under 60 minutes on 2 CPU cores: the CPU recipe took 55.2 min end to end, rendering included
(2026-11-27, 2 cores of an AMD EPYC; ``docs/training.md``, "How long it takes").

    python benchmarks/bench_train_speed.py [--config configs/pose_demo_coded_box_cpu.yaml]
        [--samples 512] [--steps 40] [--warmup 8] [--threads 2]
"""

from __future__ import annotations

import argparse
import time

# first, before torch loads: evtrack sets OpenMP's wait policy (see evtrack.runtime.openmp_wait)
import evtrack  # noqa: F401  # isort: skip
import lightning as L
import torch

from evtrack.train.config import TrainConfig
from evtrack.train.fit import build_module

VARIANTS = {
    "worker+nchw": ["data.num_workers=1", "model.channels_last=false"],
    "main+nchw": ["data.num_workers=0", "model.channels_last=false"],
    "main+nhwc": ["data.num_workers=0", "model.channels_last=true"],
    "worker+nhwc": ["data.num_workers=1", "model.channels_last=true"],
}


class StepTimer(L.Callback):
    """Wall time of every training step (batch loading included: it happens between
    ``on_train_batch_end`` and the next ``on_train_batch_start`` in the same loop)."""

    def __init__(self) -> None:
        self.ends: list[float] = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        self.ends.append(time.perf_counter())


def time_variant(config: TrainConfig, steps: int, warmup: int) -> float:
    """Seconds per training step, the mean over ``steps`` steps after ``warmup`` steps."""
    module, data = build_module(config)
    timer = StepTimer()
    trainer = L.Trainer(
        max_steps=warmup + steps, accelerator="cpu", devices=1, logger=False,
        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        limit_val_batches=0, num_sanity_val_steps=0, callbacks=[timer],
        use_distributed_sampler=False,
    )
    trainer.fit(module, datamodule=data)
    ends = timer.ends[warmup - 1:]
    return (ends[-1] - ends[0]) / (len(ends) - 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default="configs/pose_demo_coded_box_cpu.yaml",
                        help="training config (its data section sets image and crop size)")
    parser.add_argument("--samples", type=int, default=512,
                        help="training samples rendered into the benchmark's cache")
    parser.add_argument("--steps", type=int, default=40, help="timed steps per variant")
    parser.add_argument("--warmup", type=int, default=8, help="untimed steps first")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--cache", default="runs/cache",
                        help="render cache folder (samples are rendered once)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    args = parser.parse_args()
    if args.warmup < 2 or args.steps < 1:
        parser.error("--warmup must be >= 2 and --steps >= 1")
    torch.set_num_threads(args.threads)
    common = [f"data.train_samples={args.samples}", "data.val_samples=0",
              f"data.cache_dir={args.cache}"]
    base = TrainConfig.from_yaml(args.config, common)
    crop = base.data.augment.crop
    size = crop.size if crop is not None else base.data.image_size
    batch = base.data.batch_size
    print(f"config {args.config}: {base.model.name}, batches of {batch} images "
          f"{size[1]}x{size[0]} from {base.data.image_size[1]}x{base.data.image_size[0]} "
          f"renders, {args.threads} torch threads")
    print(f"{'variant':14s} {'ms/step':>9s} {'images/s':>9s} {'vs ' + args.variants[0]:>18s}")
    first = None
    for name in args.variants:
        config = TrainConfig.from_yaml(args.config, common + VARIANTS[name])
        seconds = time_variant(config, args.steps, args.warmup)
        first = first or seconds
        print(f"{name:14s} {seconds * 1e3:9.1f} {batch / seconds:9.1f} "
              f"{first / seconds:17.2f}x", flush=True)


if __name__ == "__main__":
    main()
