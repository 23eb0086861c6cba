"""Dataset items, per-epoch seeding, distributed slicing and the shard cache of the data module."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack.errors import ConfigError
from evtrack.models import Cuboid
from evtrack.train import (
    AugmentConfig,
    CuboidSourceOptions,
    DataConfig,
    EpochSampler,
    PoseDataModule,
    PoseDataset,
    SyntheticCuboidSource,
)

CUBOID = Cuboid((0.1, 0.16, 0.07))
MEAN, STD = (0.5, 0.5, 0.5), (0.25, 0.25, 0.25)


def test_items_and_seeding():
    src = SyntheticCuboidSource(CUBOID, 4, (48, 64), options=CuboidSourceOptions(
        empty_probability=0))
    ds = PoseDataset(src, MEAN, STD, AugmentConfig().build(), seed=3)
    item = ds[(0, 1)]
    assert item["image"].shape == (3, 48, 64) and item["image"].dtype == torch.float32
    assert item["belief"].shape == (9, 6, 8) and item["affinity"].shape == (16, 6, 8)
    assert float(item["belief"].max()) > 0.5
    torch.testing.assert_close(ds[(0, 1)]["image"], item["image"])  # same key, same bytes
    assert not torch.equal(ds[(1, 1)]["image"], item["image"])  # another epoch, other augment
    plain = PoseDataset(src, MEAN, STD)[1]["image"]
    expected = (src[1].image.astype(np.float32) / 255 - 0.5) / 0.25
    np.testing.assert_allclose(plain.numpy(), expected.transpose(2, 0, 1), atol=1e-6)


def test_epoch_sampler_shuffles_per_epoch_and_slices_ranks(monkeypatch):
    s = EpochSampler(10, shuffle=True, seed=1)
    e0 = list(s)
    assert sorted(i for _, i in e0) == list(range(10)) and {e for e, _ in e0} == {0}
    assert list(s) == e0
    s.set_epoch(1)
    e1 = list(s)
    assert {e for e, _ in e1} == {1} and [i for _, i in e1] != [i for _, i in e0]
    keys = []
    for rank in range(3):
        monkeypatch.setattr(EpochSampler, "_rank_world", staticmethod(lambda r=rank: (r, 3)))
        part = list(s)
        assert len(part) == len(s) == 4
        keys += [i for _, i in part]
    assert set(keys) == set(range(10))  # 12 slots: every index, two repeated
    monkeypatch.undo()
    assert [i for _, i in EpochSampler(5, shuffle=False)] == [0, 1, 2, 3, 4]


def test_data_module_renders_the_cache_once(tmp_path):
    cfg = DataConfig(train_samples=6, val_samples=3, image_size=(48, 64), batch_size=4,
                     cache_dir=str(tmp_path / "cache"), samples_per_shard=4)
    dm = PoseDataModule(cfg, "box", CUBOID, mean=MEAN, std=STD)
    dm.prepare_data()
    folders = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert len(folders) == 2 and folders[0].startswith("train_") and folders[1].startswith("val_")
    stamp = [(p, p.stat().st_mtime_ns) for p in (tmp_path / "cache").rglob("*.h5")]
    dm.prepare_data()  # second call: nothing rewritten
    assert stamp == [(p, p.stat().st_mtime_ns) for p in (tmp_path / "cache").rglob("*.h5")]
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (4, 3, 48, 64) and batch["belief"].shape == (4, 9, 6, 8)
    assert len(dm.val_dataloader()) == 1
    assert "cached samples" in dm.describe()
    other = PoseDataModule(DataConfig(train_samples=6, val_samples=3, image_size=(48, 64),
                                      seed=9, cache_dir=str(tmp_path / "cache")), "box", CUBOID)
    other.prepare_data()  # another seed: another fingerprint, another folder
    assert len(list((tmp_path / "cache").iterdir())) == 3


def test_bad_source_options_name_their_key():
    cfg = DataConfig(train_samples=2, val_samples=2, image_size=(48, 64),
                     options={"max_instances": 2}, val_options={"max_instances": 0})
    dm = PoseDataModule(cfg, "box", CUBOID, mean=MEAN, std=STD)
    assert dm._source("train").options.max_instances == 2
    with pytest.raises(ConfigError, match=r"^data\.val_options: max_instances: must be >= 1, "
                       r"got 0"):
        dm._source("val")


def test_render_workers_fill_the_same_cache(tmp_path, monkeypatch):
    """``data.render_workers`` renders the cache in processes: same folder (the fingerprint
    ignores the worker count), same samples."""
    from evtrack.train import data as data_module

    asked = []
    real = data_module.write_shards

    def recording(*args, **kwargs):
        asked.append(kwargs["workers"])
        return real(*args, **kwargs)

    monkeypatch.setattr(data_module, "write_shards", recording)
    caches = []
    for workers in (0, 2):
        cfg = DataConfig(train_samples=6, val_samples=0, image_size=(48, 64), batch_size=4,
                         cache_dir=str(tmp_path / f"cache{workers}"), samples_per_shard=2,
                         render_workers=workers)
        dm = PoseDataModule(cfg, "box", CUBOID, mean=MEAN, std=STD)
        dm.prepare_data()
        dm.setup("fit")
        caches.append(dm)
    assert asked == [0, 2]
    serial, parallel = (c.train_source for c in caches)
    assert serial.folder.name == parallel.folder.name
    for i in range(6):
        np.testing.assert_array_equal(serial[i].image, parallel[i].image)
        np.testing.assert_array_equal(serial[i].keypoints, parallel[i].keypoints)
    with pytest.raises(ConfigError, match="render_workers: must be >= 0"):
        DataConfig(render_workers=-1)


def test_lightning_advances_the_sampler_epoch():
    import lightning as L

    from evtrack.train import TrainConfig, build_module

    cfg = TrainConfig.from_dict({
        "object": {"name": "box", "dimensions": [0.1, 0.16, 0.07]},
        "model": {"name": "dope_lite_tiny"},
        "data": {"train_samples": 4, "val_samples": 0, "image_size": [48, 64], "batch_size": 2},
    })
    module, dm = build_module(cfg)
    seen = []

    class Spy(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            seen.append(trainer.train_dataloader.sampler.epoch)

    L.Trainer(max_epochs=3, accelerator="cpu", logger=False, enable_checkpointing=False,
              enable_progress_bar=False, enable_model_summary=False, callbacks=[Spy()],
              use_distributed_sampler=False).fit(module, dm)
    assert seen == [0, 0, 1, 1, 2, 2]  # so each epoch's augmentation differs


def test_persistent_loader_workers_see_each_epoch():
    """The loader's workers live for the whole run; the epoch still reaches them (through the
    sampler's keys), so 2 workers give the batches of the main process, epoch by epoch."""
    import lightning as L

    from evtrack.train import TrainConfig, build_module

    batches = {}
    for workers in (0, 2):
        cfg = TrainConfig.from_dict({
            "object": {"name": "box", "dimensions": [0.1, 0.16, 0.07]},
            "model": {"name": "dope_lite_tiny"},
            "data": {"train_samples": 4, "val_samples": 0, "image_size": [48, 64],
                     "batch_size": 2, "num_workers": workers},
        })
        module, dm = build_module(cfg)
        seen: list[torch.Tensor] = []

        class Spy(L.Callback):
            def __init__(self, into: list[torch.Tensor]) -> None:
                self.into = into

            def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
                self.into.append(batch["image"].clone())

        trainer = L.Trainer(max_epochs=3, accelerator="cpu", logger=False,
                            enable_checkpointing=False, enable_progress_bar=False,
                            enable_model_summary=False, callbacks=[Spy(seen)],
                            use_distributed_sampler=False)
        trainer.fit(module, dm)
        assert trainer.train_dataloader.persistent_workers == (workers > 0)
        batches[workers] = seen
    assert len(batches[0]) == len(batches[2]) == 6
    for a, b in zip(batches[0], batches[2], strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.equal(batches[0][0], batches[0][2])  # epoch 1 is augmented anew
