"""Simulation configs: defaults, YAML files, and errors that name the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from evtrack.errors import ConfigError
from evtrack.sim.config import SimConfig, TrajectoryConfig, load_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize("name", ["sim_regular.yaml", "sim_faster.yaml", "sim_training.yaml"])
def test_shipped_configs_load(name: str) -> None:
    cfg = load_config(CONFIGS / name)
    assert cfg.camera.width == 640 and cfg.render.render_hz == 500.0
    assert SimConfig.from_dict(cfg.to_dict()) == cfg


def test_presets() -> None:
    assert load_config(CONFIGS / "sim_faster.yaml").trajectory.preset == "faster"
    reg, fast = TrajectoryConfig(preset="regular"), TrajectoryConfig(preset="faster")
    assert fast.linear_speed > reg.linear_speed and fast.angular_speed > reg.angular_speed
    assert TrajectoryConfig(preset="faster", linear_speed=0.1).linear_speed == 0.1


def test_defaults_and_camera() -> None:
    cfg = SimConfig()
    cam = cfg.camera.camera()
    assert (cam.cx, cam.cy) == (319.5, 239.5) and cam.size == (640, 480)
    small = cfg.camera.resized(64, 48).camera()
    assert small.fx == pytest.approx(61.5) and (small.cx, small.cy) == (31.5, 23.5)


@pytest.mark.parametrize("data, match", [
    ({"durration": 1.0}, r"unknown field\(s\) \['durration'\]"),
    ({"events": {"threshold_on": "high"}}, r"events.threshold_on: expected a number"),
    ({"events": {"threshold_on": -0.1}}, r"^x.yaml: events.threshold_on: must be > 0, got -0.1$"),
    ({"trajectory": {"preset": "slow"}},
     r"trajectory.preset: must be one of \['regular', 'faster'\], got 'slow'"),
    ({"scene": {"light_direction": [1, 2]}}, r"scene.light_direction: expected a list of 3"),
    ({"render": {"adaptive": "yes"}}, r"render.adaptive: expected true or false"),
    ({"camera": 5}, r"camera: expected a mapping"),
    ({"duration": 0}, r"^x.yaml: duration: must be > 0 s, got 0"),
    ({"render": {"render_hz": 30.0}}, r"render_hz .* must be at least frames.rgb_hz"),
    ({"trajectory": {"z_range": [1.0, 0.5]}},
     r"^x.yaml: trajectory.z_range: must be 0 < near < far, got \(1.0, 0.5\)$"),
    ({"trajectory": {"linear_speed": 0}}, r"trajectory.linear_speed: must be > 0 m/s, got 0"),
    ({"frames": {"exposure": 1.5}}, r"frames.exposure: must be in \(0, 1\], got 1.5"),
    ({"scene": {"light_direction": [1, 2, "up"]}},
     r"scene.light_direction\[2\]: expected a number, got 'up'"),
])
def test_errors_name_the_field(data, match) -> None:
    with pytest.raises(ConfigError, match=match):
        SimConfig.from_dict(data, source="x.yaml")


def test_scientific_notation_that_yaml_reads_as_a_string_is_a_number(tmp_path) -> None:
    path = tmp_path / "sci.yaml"
    path.write_text("render: {render_hz: 4e3}\nevents: {threshold_on: 5e-1}\n")
    cfg = load_config(path)
    assert cfg.render.render_hz == 4000.0 and cfg.events.threshold_on == 0.5


def test_load_errors(tmp_path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("duration: [1,\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_config(bad)
    ok = tmp_path / "ok.yaml"
    ok.write_text("duration: 0.5\ntrajectory:\n  preset: faster\n")
    cfg = load_config(ok)
    assert cfg.duration == 0.5 and cfg.trajectory.linear_speed == 0.8


def test_trajectory_preset_names_are_the_presets() -> None:
    from typing import get_args

    from evtrack.sim.config import TRAJECTORY_PRESETS, TrajectoryPreset

    assert set(get_args(TrajectoryPreset)) == set(TRAJECTORY_PRESETS)


def test_checks_hold_for_configs_built_in_code() -> None:
    from evtrack.sim.config import EventConfig, FrameConfig

    with pytest.raises(ConfigError, match=r"^EventConfig.refractory_us: must be >= 0 µs"):
        EventConfig(refractory_us=-1.0)
    with pytest.raises(ConfigError, match=r"^FrameConfig.rgb_hz: must be > 0 Hz"):
        FrameConfig(rgb_hz=float("nan"))
    with pytest.raises(ConfigError, match=r"^TrajectoryConfig.preset: must be one of"):
        TrajectoryConfig(preset="slow")


def test_to_yaml_round_trips(tmp_path) -> None:
    cfg = SimConfig.from_dict({"duration": 0.5, "scene": {"distractor_kinds": ["can"]}})
    cfg.to_yaml(tmp_path / "cfg.yaml")
    assert load_config(tmp_path / "cfg.yaml") == cfg


def test_distractor_kinds_load_from_yaml_as_a_list():
    from evtrack.sim.config import SimConfig

    cfg = SimConfig.from_dict({"scene": {"distractor_kinds": ["can"]}})
    assert cfg.scene.distractor_kinds == ("can",)
    with pytest.raises(ConfigError, match="distractor_kinds"):
        SimConfig.from_dict({"scene": {"distractor_kinds": "can"}})
