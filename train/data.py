"""Dataset and ``LightningDataModule``: samples -> augmented, normalised images + targets.

Reproducibility: the augmentation of sample ``i`` in epoch ``e`` is seeded by
``(seed, e, i)``, so runs repeat exactly whatever the number of workers. The epoch reaches the
dataset through :class:`EpochSampler`, whose ``set_epoch`` Lightning calls at each epoch and
which yields ``(epoch, index)`` keys. Under ``torch.distributed`` the sampler gives each rank
its own slice (Lightning's sampler replacement is turned off by ``evtrack train``).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler
from tqdm.auto import tqdm

from evtrack.models.cuboid import Cuboid
from evtrack.train.augment import AugmentConfig, Compose
from evtrack.train.samples import SampleSource, SourceSpec, build_source
from evtrack.train.shards import INDEX_NAME, ShardSource, fingerprint, write_shards
from evtrack.train.targets import TargetConfig, make_targets

if TYPE_CHECKING:
    from evtrack.train.config import DataConfig

__all__ = ["PoseDataset", "EpochSampler", "PoseDataModule"]


class PoseDataset(Dataset):
    """Training items from a sample source.

    Args:
        source: any :class:`~evtrack.train.samples.SampleSource`.
        mean, std: input normalisation (RGB in [0, 1]).
        augment: transforms for training (``None`` for validation).
        targets: target shape.
        seed: augmentation seed.

    Items (index ``i`` or key ``(epoch, i)``) are dicts with ``image`` (3, H, W) float32,
    ``belief`` (9, H/8, W/8) and ``affinity`` (16, H/8, W/8) float32 tensors.
    """

    def __init__(
        self,
        source: SampleSource,
        mean: tuple[float, float, float],
        std: tuple[float, float, float],
        augment: Compose | None = None,
        targets: TargetConfig | None = None,
        seed: int = 0,
    ) -> None:
        self.source = source
        self.mean = np.asarray(mean, np.float32)
        self.std = np.asarray(std, np.float32)
        self.augment = augment
        self.targets = targets or TargetConfig()
        self.seed = int(seed)

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor]:
        epoch, index = key if isinstance(key, tuple) else (0, key)
        sample = self.source[int(index)].check(f"source sample {index}")
        if self.augment is not None:
            rng = np.random.default_rng([self.seed, int(epoch), int(index)])
            sample = self.augment(sample, rng)
        h, w = sample.image.shape[:2]
        belief, affinity = make_targets(sample.keypoints, (h, w), self.targets)
        x = (sample.image.astype(np.float32) / 255.0 - self.mean) / self.std
        return {
            "image": torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1))),
            "belief": torch.from_numpy(belief),
            "affinity": torch.from_numpy(affinity),
        }


class EpochSampler(Sampler):
    """Yields ``(epoch, index)`` keys, shuffled per epoch by ``(seed, epoch)``.

    Under an initialised ``torch.distributed`` group each rank takes every
    ``world_size``-th key (the total is padded by repetition to a multiple of the world size).
    """

    def __init__(self, size: int, shuffle: bool = True, seed: int = 0) -> None:
        self.size = int(size)
        self.shuffle = shuffle
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    @staticmethod
    def _rank_world() -> tuple[int, int]:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            return torch.distributed.get_rank(), torch.distributed.get_world_size()
        return 0, 1

    def _indices(self) -> np.ndarray:
        if self.shuffle:
            return np.random.default_rng([self.seed, self.epoch]).permutation(self.size)
        return np.arange(self.size)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        rank, world = self._rank_world()
        idx = self._indices()
        if world > 1 and len(idx):
            idx = np.resize(idx, -(-len(idx) // world) * world)[rank::world]
        return iter([(self.epoch, int(i)) for i in idx])

    def __len__(self) -> int:
        _, world = self._rank_world()
        return -(-self.size // world)


class PoseDataModule(L.LightningDataModule):
    """Training and validation data for one object.

    Args:
        config: the ``data`` section (:class:`~evtrack.train.config.DataConfig`).
        object_name, cuboid, mesh: the object.
        mean, std: input normalisation.

    With ``config.cache_dir`` set, :meth:`prepare_data` (run once, on the main process)
    renders both sources into shard folders named by a fingerprint of everything that
    determines the samples, and :meth:`setup` reads from them; otherwise samples are made on
    the fly in the loader workers.
    """

    def __init__(
        self,
        config: DataConfig,
        object_name: str,
        cuboid: Cuboid,
        mesh: str | None = None,
        mean: tuple[float, float, float] = (0.485, 0.456, 0.406),
        std: tuple[float, float, float] = (0.229, 0.224, 0.225),
    ) -> None:
        super().__init__()
        self.config = config
        self.object_name = object_name
        self.cuboid = cuboid
        self.mesh = mesh
        self.mean, self.std = tuple(mean), tuple(std)
        self.train_source: SampleSource | None = None
        self.val_source: SampleSource | None = None

    # ------------------------------------------------------------------ sources
    def _spec(self, split: str) -> tuple[str, SourceSpec]:
        c = self.config
        train = split == "train"
        kind = c.source if train or c.val_source is None else c.val_source
        own_options = not train and c.val_options is not None
        spec = SourceSpec(
            options=dict(c.val_options if own_options else c.options),
            object_name=self.object_name, cuboid=self.cuboid,
            mesh=self.mesh, num_samples=c.train_samples if train else c.val_samples,
            image_size=tuple(c.image_size), seed=c.seed if train else c.val_seed,
            options_key="data.val_options" if own_options else "data.options",
        )
        return kind, spec

    def _cache_folder(self, split: str) -> Path | None:
        if self.config.cache_dir is None:
            return None
        kind, spec = self._spec(split)
        if kind == "shards":  # already on disk
            return None
        fp = fingerprint({
            "kind": kind, "options": spec.options, "object": spec.object_name,
            "cuboid": spec.cuboid.to_dict(), "mesh": spec.mesh, "n": spec.num_samples,
            "size": spec.image_size, "seed": spec.seed,
        })
        return Path(self.config.cache_dir) / f"{split}_{fp}"

    def _source(self, split: str) -> SampleSource:
        folder = self._cache_folder(split)
        if folder is not None:
            return ShardSource(folder)
        return build_source(*self._spec(split))

    def prepare_data(self) -> None:
        """Render the shard caches that do not exist yet (no-op without ``cache_dir``)."""
        for split in ("train", "val"):
            if split == "val" and self.config.val_samples == 0:
                continue
            folder = self._cache_folder(split)
            if folder is None or (folder / INDEX_NAME).exists():
                continue
            kind, spec = self._spec(split)
            with tqdm(total=spec.num_samples, unit="sample", desc=f"rendering {split} cache",
                      disable=None) as bar:
                write_shards(build_source(kind, spec), folder,
                             samples_per_shard=self.config.samples_per_shard,
                             fingerprint_value=folder.name,
                             workers=self.config.render_workers,
                             progress=lambda done, total: bar.update(done - bar.n))

    def setup(self, stage: str | None = None) -> None:
        if self.train_source is None:
            self.train_source = self._source("train")
        if self.val_source is None and self.config.val_samples:
            self.val_source = self._source("val")

    # ------------------------------------------------------------------ loaders
    def _loader(self, dataset: PoseDataset, shuffle: bool, seed: int) -> DataLoader:
        c = self.config
        return DataLoader(
            dataset, batch_size=c.batch_size, sampler=EpochSampler(len(dataset), shuffle, seed),
            # Workers live for the whole run: re-forked every epoch they made each epoch wait
            # ~0.1 s more for its first batch (2 workers on 2 cores, epochs of 8 batches of
            # 64: 1.03-1.28 s per epoch re-forked, 0.87-1.14 s persistent).
            num_workers=c.num_workers, persistent_workers=c.num_workers > 0,
            pin_memory=torch.cuda.is_available(), drop_last=False,
        )

    def train_dataloader(self) -> DataLoader:
        c = self.config
        augment = c.augment.build() if isinstance(c.augment, AugmentConfig) else c.augment
        ds = PoseDataset(self.train_source, self.mean, self.std, augment, c.targets, c.seed)
        return self._loader(ds, shuffle=True, seed=c.seed)

    def val_dataloader(self) -> DataLoader | list:
        if self.val_source is None:
            return []
        ds = PoseDataset(self.val_source, self.mean, self.std, None, self.config.targets)
        return self._loader(ds, shuffle=False, seed=self.config.val_seed)

    def describe(self) -> str:
        """One line for the model card's training data."""
        parts = [f"train: {self.train_source.description}" if self.train_source else ""]
        if self.val_source is not None:
            parts.append(f"val: {self.val_source.description}")
        aug = self.config.augment
        if isinstance(aug, AugmentConfig):
            on = [n for n in ("crop", "scale", "color", "occlusion", "motion_blur", "noise")
                  if aug.enabled and getattr(aug, n) is not None]
            parts.append(f"augmentation: {', '.join(on) or 'none'}")
        return "; ".join(p for p in parts if p)
