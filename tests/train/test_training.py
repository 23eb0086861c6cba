"""Training end to end: a tiny overfit, a full run with resume, the train and export commands."""

from __future__ import annotations

import csv
import math

import lightning as L
import numpy as np
import pytest
import torch

from evtrack.cli import main
from evtrack.errors import ConfigError
from evtrack.models import (
    Cuboid,
    OnnxPoseEstimator,
    WeightsError,
    WeightsRecord,
    create,
    load_model,
)
from evtrack.train import (
    CuboidSourceOptions,
    LossConfig,
    OptimConfig,
    PoseDataset,
    PoseLightningModule,
    SyntheticCuboidSource,
    TrainConfig,
    corner_identity_hits,
    corner_identity_loss,
    run_training,
)

CUBOID = Cuboid((0.1, 0.16, 0.07))
MEAN, STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


class LossRecorder(L.Callback):
    def __init__(self):
        self.losses = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.losses.append(float(outputs["loss"]))


def test_tiny_overfit_loss_decreases_below_the_all_zero_baseline():
    torch.manual_seed(0)
    src = SyntheticCuboidSource(CUBOID, 4, (64, 96), options=CuboidSourceOptions(
        empty_probability=0, distance_range=(1.8, 2.5), distractor_boxes=0))
    ds = PoseDataset(src, MEAN, STD)  # no augmentation: the same 4 images every step
    loader = torch.utils.data.DataLoader(ds, batch_size=4)
    net = create("dope_lite_tiny")
    record = WeightsRecord(arch="dope_lite_tiny", object_name="box", cuboid=CUBOID)
    module = PoseLightningModule(net, record, OptimConfig(lr=5e-3, warmup_steps=0,
                                                          schedule="constant"))
    recorder = LossRecorder()
    trainer = L.Trainer(max_steps=60, accelerator="cpu", logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[recorder])
    trainer.fit(module, loader)
    batch = next(iter(loader))
    zeros = [(torch.zeros_like(batch["belief"]), torch.zeros_like(batch["affinity"]))]
    zero_loss = float(module.compute_loss(zeros, batch["belief"], batch["affinity"])[0])
    first, last = recorder.losses[0], float(np.mean(recorder.losses[-5:]))
    assert len(recorder.losses) == 60
    assert last < 0.1 * first
    assert last < 0.8 * zero_loss  # it learned peaks, not just to output zeros


def test_channels_last_training_step_matches_the_contiguous_one(tmp_path):
    src = SyntheticCuboidSource(CUBOID, 4, (64, 96), options=CuboidSourceOptions(
        empty_probability=0, distance_range=(1.8, 2.5), distractor_boxes=0))
    batch = next(iter(torch.utils.data.DataLoader(PoseDataset(src, MEAN, STD), batch_size=4)))
    record = WeightsRecord(arch="dope_lite_tiny", object_name="box", cuboid=CUBOID)
    results = []
    for channels_last in (False, True):
        torch.manual_seed(0)
        module = PoseLightningModule(create("dope_lite_tiny"), record,
                                     channels_last=channels_last)
        conv = module.net.stem[0].weight
        assert conv.is_contiguous(memory_format=torch.channels_last) == channels_last
        loss = module._common_step(batch, "val")
        loss.backward()
        grads = {n: p.grad.clone() for n, p in module.net.named_parameters()}
        path = module.export_weights(str(tmp_path / f"w{int(channels_last)}.pt"))
        results.append((float(loss), grads, load_model(path)[0].state_dict()))
    (l0, g0, s0), (l1, g1, s1) = results
    assert l1 == pytest.approx(l0, rel=1e-5)
    # the output layer's gradient is well conditioned: equal to float rounding. Deeper layers
    # are not compared: BatchNorm's backward at initialisation on this batch differs from a
    # float64 reference by up to ~10% (one thread, NHWC) or 0.2% (NCHW) of a layer's largest
    # entry, which says more about float32 than about the layout
    out = g0["stages.0.out.weight"]
    torch.testing.assert_close(g1["stages.0.out.weight"], out, rtol=0,
                               atol=1e-3 * float(out.abs().max()))
    assert s1.keys() == s0.keys()
    for k in s0:  # the same initial weights, saved contiguous either way
        assert s1[k].is_contiguous()
        torch.testing.assert_close(s1[k], s0[k])


class LrRecorder(L.Callback):
    def __init__(self):
        self.lrs = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.lrs.append(trainer.optimizers[0].param_groups[0]["lr"])


@pytest.mark.parametrize("schedule_by", ["steps", "time"])
def test_a_time_schedule_ends_its_cosine_when_max_time_stops_the_run(schedule_by):
    src = SyntheticCuboidSource(CUBOID, 2, (32, 32), options=CuboidSourceOptions(
        empty_probability=0, distance_range=(1.8, 2.5), distractor_boxes=0))
    loader = torch.utils.data.DataLoader(PoseDataset(src, MEAN, STD), batch_size=2)
    record = WeightsRecord(arch="dope_lite_tiny", object_name="box", cuboid=CUBOID)
    optim = OptimConfig(lr=1e-3, warmup_steps=0, schedule_by=schedule_by)
    module = PoseLightningModule(create("dope_lite_tiny"), record, optim)
    recorder = LrRecorder()
    trainer = L.Trainer(max_epochs=100_000, max_time={"seconds": 2}, accelerator="cpu",
                        logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[recorder])
    trainer.fit(module, loader)
    lrs = recorder.lrs
    assert trainer.current_epoch < 100_000 - 1 and len(lrs) > 5  # the time budget stopped it
    if schedule_by == "steps":  # planned for 100k epochs: hardly started its cosine
        assert lrs[-1] > 0.99e-3
    else:  # followed the clock: annealed to the end, monotonically
        assert lrs[-1] < 0.1e-3
        assert all(b <= a for a, b in zip(lrs, lrs[1:], strict=False))


def test_a_time_schedule_needs_max_time():
    src = SyntheticCuboidSource(CUBOID, 2, (32, 32))
    loader = torch.utils.data.DataLoader(PoseDataset(src, MEAN, STD), batch_size=2)
    record = WeightsRecord(arch="dope_lite_tiny", object_name="box", cuboid=CUBOID)
    module = PoseLightningModule(create("dope_lite_tiny"), record,
                                 OptimConfig(schedule_by="time"))
    trainer = L.Trainer(max_steps=2, accelerator="cpu", logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False)
    with pytest.raises(ConfigError, match="needs trainer.max_time"):
        trainer.fit(module, loader)
    with pytest.raises(ConfigError, match="schedule_by must be"):
        OptimConfig(schedule_by="epochs")


def test_module_rejects_a_record_of_another_network():
    net = create("dope_lite_tiny")
    with pytest.raises(ConfigError, match="record describes dope_lite_small"):
        PoseLightningModule(net, WeightsRecord(arch="dope_lite_small", object_name="box",
                                               cuboid=CUBOID))
    with pytest.raises(ConfigError, match="evtrack.models.create"):
        PoseLightningModule(torch.nn.Conv2d(3, 25, 1),
                            WeightsRecord(arch="x", object_name="box", cuboid=CUBOID))


def test_loss_is_the_stage_sum_of_mses():
    module = PoseLightningModule(create("dope_lite_tiny"),
                                 WeightsRecord(arch="dope_lite_tiny", object_name="b",
                                               cuboid=CUBOID),
                                 loss=LossConfig(affinity_weight=0.5, last_stage_weight=2.0,
                                                 positive_weight=0.0))
    b, a = torch.ones(1, 9, 2, 2), torch.zeros(1, 16, 2, 2)
    stages = [(torch.zeros_like(b), torch.ones_like(a)), (torch.full_like(b, 3.0),
                                                          torch.full_like(a, 2.0))]
    total, lb, la, li = module.compute_loss(stages, b, a)
    assert float(li) == 0.0                # identity term off by default
    assert float(lb) == pytest.approx(1 + 2 * 4)
    assert float(la) == pytest.approx(1 + 2 * 4)
    assert float(total) == pytest.approx(9 + 0.5 * 9)


@pytest.mark.parametrize("shared", [False, True])
def test_positive_weighting_matches_a_cell_by_cell_sum(shared):
    pw = 7.0
    module = PoseLightningModule(create("dope_lite_tiny"),
                                 WeightsRecord(arch="dope_lite_tiny", object_name="b",
                                               cuboid=CUBOID),
                                 loss=LossConfig(positive_weight=pw,
                                                 shared_positive_weight=shared))
    g = torch.Generator().manual_seed(0)
    b = torch.rand(2, 9, 3, 4, generator=g)
    a = torch.randn(2, 16, 3, 4, generator=g)
    a[:, :, 1:] = 0.0                      # only row 0 is inside the discs
    a[0, 2, 0, 1] = 0.0                    # a cell where dx = 0 but dy != 0 is still in the disc
    pb, pa = torch.rand(2, 9, 3, 4, generator=g), torch.randn(2, 16, 3, 4, generator=g)
    _, lb, la, _ = module.compute_loss([(pb, pa)], b, a)
    expect_b = expect_a = 0.0
    for n, c, i, j in np.ndindex(*b.shape):
        target = max(float(b[n, k, i, j]) for k in range(9)) if shared else float(b[n, c, i, j])
        expect_b += (1 + pw * target) * float(pb[n, c, i, j] - b[n, c, i, j]) ** 2
    for n, c, i, j in np.ndindex(*a.shape):
        k = c // 2  # affinity weights are per corner whether belief weights are shared or not
        inside = bool(a[n, 2 * k, i, j] != 0 or a[n, 2 * k + 1, i, j] != 0)
        expect_a += (1 + pw * inside) * float(pa[n, c, i, j] - a[n, c, i, j]) ** 2
    assert float(lb) == pytest.approx(expect_b / b.numel(), rel=1e-5)
    assert float(la) == pytest.approx(expect_a / a.numel(), rel=1e-5)


def test_corner_identity_loss_matches_a_cell_by_cell_cross_entropy():
    g = torch.Generator().manual_seed(1)
    target = torch.rand(2, 9, 3, 4, generator=g) * 0.9
    pred = torch.rand(2, 9, 3, 4, generator=g)
    temperature, min_target = 6.0, 0.6
    got = corner_identity_loss(pred, target, temperature, min_target)
    terms = []
    for n, i, j in np.ndindex(2, 3, 4):
        corner = [float(target[n, k, i, j]) for k in range(8)]
        if max(corner) < min_target:
            continue
        label = int(np.argmax(corner))
        logits = [temperature * float(pred[n, k, i, j]) for k in range(8)]
        terms.append(-(logits[label] - math.log(sum(math.exp(v) for v in logits))))
    assert terms, "the draw should score some cells"
    assert float(got) == pytest.approx(float(np.mean(terms)), rel=1e-5)
    # no scored cell: zero, not NaN
    assert float(corner_identity_loss(pred, target * 0.1, temperature, min_target)) == 0.0


def test_identity_term_penalises_a_map_firing_on_another_corner():
    module = PoseLightningModule(create("dope_lite_tiny"),
                                 WeightsRecord(arch="dope_lite_tiny", object_name="b",
                                               cuboid=CUBOID),
                                 loss=LossConfig(identity_weight=1.0))
    target = torch.zeros(1, 9, 4, 4)
    target[0, 0, 1, 1] = 1.0               # corner 0 at (1, 1), corner 1 at (2, 2)
    target[0, 1, 2, 2] = 1.0
    affinity = torch.zeros(1, 16, 4, 4)
    right = target.clone()
    confused = target.clone()
    confused[0, 0, 2, 2] = 1.0             # map 0 also fires on corner 1
    confused[0, 1, 1, 1] = 1.0
    li_right = float(module.compute_loss([(right, affinity)], target, affinity)[3])
    li_confused = float(module.compute_loss([(confused, affinity)], target, affinity)[3])
    # logits 10 (right map), 10 (the confused map) and six 0s; right: one 10 and seven 0s
    assert li_confused == pytest.approx(math.log(2 + 6 * math.exp(-10.0)), rel=1e-5)
    assert li_right == pytest.approx(math.log(1 + 7 * math.exp(-10.0)), abs=1e-6)


def test_corner_identity_hits_reads_the_maps_at_each_corner_peak():
    target = torch.zeros(1, 9, 6, 6)
    for k, (i, j) in enumerate([(0, 0), (0, 5), (5, 0), (5, 5)]):
        target[0, k, i, j] = 1.0
        target[0, k, 1 if i == 0 else 4, j] = 0.6      # the Gaussian's shoulder: not scored
    pred = torch.zeros(1, 9, 6, 6)
    pred[0, 0, 0, 0] = 0.9                          # corner 0: right
    pred[0, 1, 0, 5] = 0.4
    pred[0, 3, 0, 5] = 0.5                          # corner 1: map 3 is stronger, a miss
    pred[0, 2, 5, 0] = 0.7                          # corner 2: right
    pred[0, 8, 5, 5] = 5.0                          # corner 3: only the centroid map fires;
    pred[0, 3, 5, 5] = 0.1                          # among the corner maps, map 3 wins
    assert corner_identity_hits(pred, target) == (3, 4)
    assert corner_identity_hits(pred, torch.zeros_like(target)) == (0, 0)


def test_negative_loss_weights_are_refused():
    with pytest.raises(ConfigError, match="loss"):
        LossConfig(positive_weight=-1.0)


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs")
    cfg = TrainConfig.from_dict({
        "object": {"name": "box", "dimensions": [0.1, 0.16, 0.07]},
        "model": {"name": "dope_lite_tiny"},
        "data": {"train_samples": 12, "val_samples": 4, "image_size": [48, 64],
                 "batch_size": 4, "num_workers": 0, "cache_dir": str(out / "cache")},
        "optim": {"warmup_steps": 2},
        "trainer": {"max_epochs": 2, "accelerator": "cpu", "log_every_n_steps": 1},
        "output_dir": str(out),
    })
    return cfg, run_training(cfg, verbose=False)


def test_run_writes_checkpoints_logs_weights_and_card(trained_run):
    cfg, result = trained_run
    run = result.run_dir
    assert run == cfg.output_dir / __import__("pathlib").Path(cfg.name)
    assert (run / "config.yaml").is_file()
    assert result.last_checkpoint.name == "last.ckpt" and result.best_checkpoint.is_file()
    rows = list(csv.DictReader(open(next(run.glob("logs/version_*/metrics.csv")))))
    assert any(r.get("val/loss") for r in rows) and any(r.get("train/loss_step") for r in rows)
    # the checkpoint is plain data: weights_only loading works
    ckpt = torch.load(result.last_checkpoint, weights_only=True)
    assert ckpt["hyper_parameters"]["record"]["arch"] == "dope_lite_tiny"
    net, record = load_model(result.weights)
    assert record.object_name == "box" and record.training["epochs"] == 2
    assert "val/loss" in record.metrics and record.training["steps"] == 6
    assert "OpenCV-drawn" in record.training_data
    card = result.card.read_text()
    assert "val/keypoint_recall" in card and "wall_time_s" in card and "max_epochs: 2" in card
    # the Lightning checkpoint loads the same way as the weights file
    same = create("dope_lite_tiny", weights=result.best_checkpoint)
    torch.testing.assert_close(same.state_dict(), net.state_dict())
    with pytest.raises(WeightsError, match="object 'box', not 'mug'"):
        create("dope_lite_tiny", weights=result.best_checkpoint, object_name="mug")


def test_resume_continues_from_the_last_checkpoint(trained_run):
    cfg, first = trained_run
    # last.ckpt holds the whole state a resume needs, not only the weights
    state = torch.load(first.last_checkpoint, weights_only=True)
    assert state["optimizer_states"] and state["loops"] and state["callbacks"]
    more = TrainConfig.from_dict({**cfg.to_dict(), "trainer": {**cfg.trainer, "max_epochs": 3}})
    result = run_training(more, resume="auto", verbose=False)
    record = load_model(result.weights)[1]
    assert record.training["epochs"] == 3 and record.training["steps"] == 9  # 6 + 3, not 9 + 6
    with pytest.raises(ConfigError, match="not found"):
        run_training(more, resume=str(cfg.output_dir) + "/missing.ckpt", verbose=False)


def test_init_weights_starts_from_trained_weights_with_a_fresh_schedule(trained_run, tmp_path):
    cfg, first = trained_run
    base = {**cfg.to_dict(), "output_dir": str(tmp_path), "run_name": "fine"}
    tuned = TrainConfig.from_dict({**base, "model": {**base["model"],
                                                     "init_weights": str(first.weights)},
                                   "trainer": {**cfg.trainer, "max_epochs": 1}})
    from evtrack.train.fit import build_module

    module, _ = build_module(tuned)
    start, _ = load_model(first.weights)
    torch.testing.assert_close(module.net.state_dict(), start.state_dict())  # not random
    assert module.net.training
    result = run_training(tuned, verbose=False)
    record = load_model(result.weights)[1]
    assert record.training["epochs"] == 1 and record.training["steps"] == 3  # a fresh count
    # weights of another object, a missing file, another input normalisation: refused
    for change, error, text in (
        ({"object": {**base["object"], "name": "mug"}}, WeightsError, "not 'mug'"),
        ({"model": {**base["model"], "init_weights": str(tmp_path / "no.pt")}}, ConfigError,
         "not found"),
        ({"model": {**base["model"], "init_weights": str(first.weights),
                    "mean": [0.5, 0.5, 0.5]}}, WeightsError, "mean/std"),
    ):
        bad = {**base, "model": {**base["model"], "init_weights": str(first.weights)}, **change}
        with pytest.raises(error, match=text):
            build_module(TrainConfig.from_dict(bad))


def test_init_transfer_starts_another_object_from_trained_weights(trained_run, tmp_path):
    cfg, first = trained_run
    base = {**cfg.to_dict(), "output_dir": str(tmp_path), "run_name": "transfer"}
    other = {**base["object"], "name": "mug", "dimensions": [0.08, 0.1, 0.09]}
    transfer = TrainConfig.from_dict({**base, "object": other,
                                      "model": {**base["model"], "init_weights": str(first.weights),
                                                "init_transfer": True}})
    from evtrack.train.fit import build_module

    module, _ = build_module(transfer)
    start, start_record = load_model(first.weights)
    torch.testing.assert_close(module.net.state_dict(), start.state_dict())
    assert module.net.training
    # the record is the new object's: its name and cuboid, not the source weights'
    assert module.record.object_name == "mug" and start_record.object_name == "box"
    assert module.record.cuboid == transfer.object.cuboid() != start_record.cuboid
    # the architecture must still match
    with pytest.raises(WeightsError, match="architecture"):
        build_module(TrainConfig.from_dict({**base, "object": other, "model": {
            **base["model"], "name": "dope_lite_small", "init_weights": str(first.weights),
            "init_transfer": True}}))
    with pytest.raises(ConfigError, match="init_weights is not"):
        TrainConfig.from_dict({**base, "model": {**base["model"], "init_transfer": True}})


def test_train_and_export_commands(trained_run, tmp_path, capsys):
    cfg, result = trained_run
    config_file = result.run_dir / "config.yaml"
    assert main(["train", "--config", str(config_file), "--print-config",
                 "--set", "trainer.max_epochs=7"]) == 0
    assert "max_epochs: 7" in capsys.readouterr().out
    assert main(["train", "--config", str(tmp_path / "none.yaml")]) == 1
    assert "config file not found" in capsys.readouterr().err
    onnx_path = tmp_path / "box.onnx"
    # last.ckpt: the resume test (same run folder) may have replaced the best checkpoint
    assert main(["export", "pose", "--weights", str(result.last_checkpoint),
                 "--out", str(onnx_path)]) == 0
    assert "exported dope_lite_tiny for object 'box'" in capsys.readouterr().out
    est = OnnxPoseEstimator(onnx_path, np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]]))
    assert est.object_name == "box" and est.cuboid == CUBOID
    assert isinstance(est(np.zeros((48, 64, 3), np.uint8)), list)
    assert main(["export", "pose", "--weights", str(result.weights), "--out",
                 str(tmp_path / "x.onnx"), "--object", "mug"]) == 1
    assert "not 'mug'" in capsys.readouterr().err
    assert main(["export"]) == 2


def test_keypoint_metrics_judge_the_strongest_peak_of_each_channel():
    from evtrack.train.module import keypoint_metrics

    def blob(h, w, cx, cy, amp=1.0):
        yy, xx = np.mgrid[0:h, 0:w]
        return amp * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 2.0)

    target = np.zeros((1, 9, 20, 20), np.float32)
    target[0, 0] = blob(20, 20, 5, 5)
    # right corner, strongest peak: found, at 0 px
    pred = np.zeros_like(target)
    pred[0, 0] = np.maximum(blob(20, 20, 5, 5, 0.9), blob(20, 20, 15, 15, 0.5))
    assert keypoint_metrics(pred, target, 8, 0.1, 8.0)[:2] == (1, 1)
    # a peak on the right corner but a stronger one elsewhere: the decoder would pick the wrong
    # one, so it is not found
    pred[0, 0] = np.maximum(blob(20, 20, 5, 5, 0.5), blob(20, 20, 15, 15, 0.9))
    assert keypoint_metrics(pred, target, 8, 0.1, 8.0)[:2] == (0, 1)
    # two instances: each target peak takes the nearest predicted peak
    target[0, 0] = np.maximum(blob(20, 20, 5, 5), blob(20, 20, 15, 15))
    assert keypoint_metrics(pred, target, 8, 0.1, 8.0)[:2] == (2, 2)


class WeightRecorder(L.Callback):
    """The raw weights and batch-norm statistics after every optimiser step."""

    def __init__(self):
        self.states = []

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        self.states.append({k: v.detach().clone() for k, v in module.state_dict().items()
                            if v.is_floating_point()})


def test_ema_weights_follow_the_exponential_average_of_the_steps():
    from evtrack.train.fit import weight_averaging

    assert weight_averaging(OptimConfig()) is None  # off by default
    src = SyntheticCuboidSource(CUBOID, 8, (32, 48), options=CuboidSourceOptions(
        empty_probability=0, distance_range=(1.8, 2.5), distractor_boxes=0))
    loader = torch.utils.data.DataLoader(PoseDataset(src, MEAN, STD), batch_size=2)
    record = WeightsRecord(arch="dope_lite_tiny", object_name="box", cuboid=CUBOID)
    optim = OptimConfig(lr=5e-3, warmup_steps=0, schedule="constant", ema_decay=0.7,
                        ema_start_step=2)
    torch.manual_seed(0)
    module = PoseLightningModule(create("dope_lite_tiny"), record, optim)
    recorder = WeightRecorder()
    trainer = L.Trainer(max_steps=7, accelerator="cpu", logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False,
                        callbacks=[recorder, weight_averaging(optim)])
    trainer.fit(module, loader)
    steps = recorder.states
    assert len(steps) == 7
    # by hand: a copy of the weights after step 2 (0-based), then avg = 0.7 avg + 0.3 w
    expected = dict(steps[2])
    for state in steps[3:]:
        expected = {k: 0.7 * expected[k] + 0.3 * state[k] for k in expected}
    final = module.state_dict()  # the average replaces the weights when training ends
    assert any("running_mean" in k for k in expected)  # the batch-norm statistics too
    for k, v in expected.items():
        torch.testing.assert_close(final[k], v, rtol=1e-5, atol=1e-6)
    moved = max(float((steps[-1][k] - v).abs().max()) for k, v in expected.items())
    assert moved > 1e-4  # the average is not simply the last weights


def test_ema_run_validates_checkpoints_exports_and_resumes_the_average(trained_run, tmp_path):
    cfg, _ = trained_run
    base = {**cfg.to_dict(), "output_dir": str(tmp_path), "run_name": "ema",
            "optim": {**cfg.to_dict()["optim"], "ema_decay": 0.5}}
    result = run_training(TrainConfig.from_dict(base), verbose=False)
    last = torch.load(result.last_checkpoint, weights_only=True)
    raw = {k[len("net."):]: v for k, v in last["current_model_state"].items()
           if k.startswith("net.")}
    average = {k[len("net."):]: v for k, v in last["state_dict"].items() if k.startswith("net.")}
    exported, _ = load_model(result.weights)
    # the weights file is the best checkpoint's state_dict, which is the average there too
    # (the raw weights of that step are its current_model_state)
    best_ckpt = torch.load(result.best_checkpoint, weights_only=True)
    best = best_ckpt["state_dict"]
    torch.testing.assert_close(exported.state_dict(),
                               {k[len("net."):]: v for k, v in best.items()
                                if k.startswith("net.")})
    assert any(not torch.equal(v, best_ckpt["current_model_state"][k])
               for k, v in best.items() if v.is_floating_point())
    assert any(not torch.equal(raw[k], average[k]) for k in raw if raw[k].is_floating_point())
    # resuming restores both the raw weights and the average, and goes on averaging
    more = TrainConfig.from_dict({**base, "trainer": {**cfg.trainer, "max_epochs": 3}})
    again = run_training(more, resume="auto", verbose=False)
    assert load_model(again.weights)[1].training["steps"] == 9
    with pytest.raises(ConfigError, match="ema_decay must be in"):
        OptimConfig(ema_decay=1.0)
    with pytest.raises(ConfigError, match="ema_start_step"):
        OptimConfig(ema_start_step=-1)


def test_last_checkpoint_is_the_end_of_the_run_not_the_best_epoch(trained_run, tmp_path):
    """Lightning's save_last wrote last.ckpt only with a new best checkpoint; a run stopped
    between validations (max_steps, max_time) must still leave its end in last.ckpt."""
    cfg, _ = trained_run
    stopped = TrainConfig.from_dict({
        **cfg.to_dict(), "output_dir": str(tmp_path), "run_name": "stopped",
        "trainer": {**cfg.trainer, "max_epochs": 5, "max_steps": 4}})  # 3 steps per epoch
    result = run_training(stopped, verbose=False)
    last = torch.load(result.last_checkpoint, weights_only=True)
    best = torch.load(result.best_checkpoint, weights_only=True)
    assert last["global_step"] == 4 and best["global_step"] == 3  # validated after epoch 0
    assert not list(result.last_checkpoint.parent.glob("*.tmp"))
    # --resume auto goes on from step 4
    more = TrainConfig.from_dict({**stopped.to_dict(), "trainer": {**stopped.trainer,
                                                                   "max_steps": 6}})
    again = run_training(more, resume="auto", verbose=False)
    assert torch.load(again.last_checkpoint, weights_only=True)["global_step"] == 6
