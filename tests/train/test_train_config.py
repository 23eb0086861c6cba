"""Training configs: the shipped YAML files, field errors, overrides, round trips."""

from __future__ import annotations

from pathlib import Path

import pytest

from evtrack.errors import ConfigError
from evtrack.train import TrainConfig
from evtrack.train.config import apply_overrides

CONFIGS = sorted((Path(__file__).resolve().parents[2] / "configs").glob("pose_*.yaml"))
MINIMAL = {"object": {"name": "box", "dimensions": [0.1, 0.1, 0.1]}}


def test_there_are_configs_for_the_demo_and_the_four_ycb_objects():
    names = {p.stem for p in CONFIGS}
    assert {"pose_demo_box", "pose_cuboid_box"} <= names
    assert {"pose_ycb_003_cracker_box", "pose_ycb_005_tomato_soup_can",
            "pose_ycb_006_mustard_bottle", "pose_ycb_010_potted_meat_can"} <= names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_shipped_configs_load_and_round_trip(path):
    cfg = TrainConfig.from_yaml(path)
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    assert cfg.data.image_size[0] % 8 == 0


def test_ycb_config_cuboid_comes_from_the_mesh(ycb_dir, monkeypatch):
    repo = Path(__file__).resolve().parents[2]
    monkeypatch.chdir(repo)  # mesh paths are relative to the repository root
    cfg = TrainConfig.from_yaml(repo / "configs" / "pose_ycb_003_cracker_box.yaml")
    cuboid = cfg.object.cuboid()
    assert cuboid.center == (0.0, 0.0, 0.0)  # the engine's bounding-box-centred frame
    dims = sorted(cuboid.dimensions)
    assert dims == pytest.approx([0.0718, 0.164, 0.2134], abs=2e-3)


def test_defaults_fill_in():
    cfg = TrainConfig.from_dict(MINIMAL)
    assert cfg.model.name == "dope_lite_base" and cfg.data.batch_size == 16
    assert cfg.name == "box_dope_lite_base"


@pytest.mark.parametrize("data,message", [
    ({}, "missing required field(s) ['object']"),
    ({**MINIMAL, "modle": {}}, "unknown field(s) ['modle']"),
    ({**MINIMAL, "data": {"batch_size": "16"}},
     "config: data.batch_size: expected an integer, got '16'"),
    ({**MINIMAL, "data": {"image_size": [100, 320]}},
     "config: data.image_size: must be positive multiples of 8, got (100, 320)"),
    ({**MINIMAL, "data": {"image_size": [240]}},
     "config: data.image_size: expected a list of 2 values, got [240]"),
    ({**MINIMAL, "data": {"augment": {"noise": {"sigma": 1}}}}, "config: data.augment.noise"),
    ({**MINIMAL, "optim": {"schedule": "linear"}}, "optim.schedule"),
    ({**MINIMAL, "trainer": {"max_epoch": 3}}, "unknown lightning.Trainer argument"),
    ({**MINIMAL, "trainer": {"max_epochs": "abc"}},
     "config: trainer.max_epochs: expected an integer"),
    ({**MINIMAL, "trainer": {"gradient_clip_val": "x"}}, "trainer.gradient_clip_val: expected"),
    ({**MINIMAL, "trainer": {"logger": False}}, "set by evtrack train"),
    ({**MINIMAL, "logger": "wandb"},
     "config: logger: must be one of ['csv', 'tensorboard'], got 'wandb'"),
    ({"object": {"name": "x"}, "data": {"seed": 1, "val_seed": 1}}, "config: data: seed and"),
    ({**MINIMAL, "data": {"batch_size": 0}}, "config: data.batch_size: must be >= 1, got 0"),
    ({"object": {"name": "x", "mesh": "m.obj", "dimensions": [1, 1, 1]}},
     "config: object.mesh: give either mesh or dimensions, not both"),
    ({**MINIMAL, "model": {"init_transfer": True}},
     "config: model.init_transfer: is set but init_weights is not"),
    ({**MINIMAL, "trainer": {"max_epochs": True}}, "trainer.max_epochs: expected an integer"),
])
def test_bad_fields_are_named(data, message):
    with pytest.raises(ConfigError) as info:
        TrainConfig.from_dict(data)
    assert message in str(info.value)


def test_scientific_notation_that_yaml_reads_as_a_string_is_a_number(tmp_path):
    path = tmp_path / "sci.yaml"
    path.write_text("object: {name: box, dimensions: [0.1, 0.1, 0.1]}\n"
                    "optim: {lr: 1e-3}\ndata: {train_samples: 2e3}\n")
    cfg = TrainConfig.from_yaml(path)
    assert cfg.optim.lr == 0.001 and cfg.data.train_samples == 2000
    assert isinstance(cfg.data.train_samples, int)


def test_object_needs_a_mesh_or_dimensions(tmp_path):
    with pytest.raises(ConfigError, match="needs a mesh or cuboid dimensions"):
        TrainConfig.from_dict({"object": {"name": "x"}}).object.cuboid()
    with pytest.raises(ConfigError, match="mesh file not found"):
        TrainConfig.from_dict({"object": {"name": "x", "mesh": str(tmp_path / "m.obj")}}
                              ).object.cuboid()


def test_overrides_and_files(tmp_path):
    data = apply_overrides(MINIMAL, ["trainer.max_epochs=3", "data.image_size=[64, 96]",
                                     "model.kwargs.num_stages=1"])
    cfg = TrainConfig.from_dict(data)
    assert cfg.trainer["max_epochs"] == 3 and cfg.data.image_size == (64, 96)
    assert cfg.model.kwargs == {"num_stages": 1}
    assert MINIMAL == {"object": {"name": "box", "dimensions": [0.1, 0.1, 0.1]}}  # not mutated
    with pytest.raises(ConfigError, match="must look like"):
        apply_overrides(MINIMAL, ["trainer.max_epochs"])
    with pytest.raises(ConfigError, match="not a section"):
        apply_overrides(MINIMAL, ["object.name.x=1"])
    with pytest.raises(ConfigError, match="config file not found"):
        TrainConfig.from_yaml(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("object: [unclosed")
    with pytest.raises(ConfigError, match="invalid YAML"):
        TrainConfig.from_yaml(bad)
    bad.write_text("- a list")
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        TrainConfig.from_yaml(bad)


@pytest.mark.parametrize("path", [p for p in CONFIGS if p.stem.startswith("pose_ycb_")],
                         ids=lambda p: p.stem)
def test_ycb_configs_start_from_the_shipped_coded_box_network(path, monkeypatch):
    """The YCB recipe transfers from the coded box's weights: the file it names is shipped, and
    the network it builds holds those weights, not a random initialisation."""
    import torch

    from evtrack.models import load_model
    from evtrack.train.fit import _initial_network

    repo = Path(__file__).resolve().parents[2]
    monkeypatch.chdir(repo)  # init_weights is relative to the repository root
    cfg = TrainConfig.from_yaml(path)
    assert cfg.model.init_transfer and cfg.object.name.startswith(path.stem[len("pose_ycb_"):])
    net = _initial_network(cfg)
    source, record = load_model(cfg.model.init_weights)
    assert record.object_name == "coded_box" and net.training
    torch.testing.assert_close(net.state_dict(), source.state_dict())
