"""TrackerConfig: defaults, YAML, and clear errors for unknown or invalid fields."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from evtrack.configs import RenamedKeyWarning
from evtrack.errors import ConfigError
from evtrack.tracking.config import (
    DepthConfig,
    DepthFusionConfig,
    TrackerConfig,
    load_tracker_config,
)

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_shipped_yaml_equals_the_defaults() -> None:
    assert load_tracker_config(CONFIGS / "tracker.yaml").to_dict() == TrackerConfig().to_dict()


def test_defaults_use_the_fast_object_flow_and_the_slow_config_the_generic_one() -> None:
    """The tracker's flow bounds the triplet span and tolerance as configs/flow_fast.yaml does;
    configs/tracker_slow.yaml is the defaults with the flow's generic span and tolerance, every
    other field as the defaults."""
    from evtrack.flow import FlowConfig

    defaults = TrackerConfig()
    flow_fast = FlowConfig.from_yaml(CONFIGS / "flow_fast.yaml")
    assert (defaults.flow.max_span_us, defaults.flow.tolerance_rel) == (
        flow_fast.max_span_us, flow_fast.tolerance_rel) == (40_000, 0.05)
    slow = load_tracker_config(CONFIGS / "tracker_slow.yaml")
    generic = FlowConfig()
    assert (slow.flow.max_span_us, slow.flow.tolerance_rel) == (generic.max_span_us,
                                                                generic.tolerance_rel)
    assert slow.replace(flow=defaults.flow).to_dict() == defaults.to_dict()
    assert slow.flow.replace(max_span_us=defaults.flow.max_span_us,
                             tolerance_rel=defaults.flow.tolerance_rel) == defaults.flow


def test_rgbd_preset_is_the_defaults_with_both_depth_extensions() -> None:
    rgbd = load_tracker_config(CONFIGS / "tracker_rgbd.yaml")
    assert rgbd.depth_fusion.range and rgbd.depth_fusion.icp
    assert rgbd.replace(depth_fusion=DepthFusionConfig()).to_dict() == TrackerConfig().to_dict()


def test_round_trip(tmp_path) -> None:
    cfg = TrackerConfig.from_dict({"method": "frame-flow", "flow": {"roi_size": 16},
                                   "velocity_kf": {"weighting": False, "normal_flow_std": 20},
                                   "frame_flow": {"algorithm": "farneback"}})
    path = tmp_path / "t.yaml"
    cfg.to_yaml(path)
    again = TrackerConfig.from_yaml(path)
    assert again == cfg
    assert again.flow.roi_size == 16 and again.flow.window_us == 1000
    assert again.velocity_kf.weighting is False and again.velocity_kf.normal_flow is True
    assert again.velocity_kf.normal_flow_std == 20


def test_partial_sections_keep_the_other_defaults() -> None:
    cfg = TrackerConfig.from_dict({"pose_ukf": {"q_rotation": 0.5}})
    assert cfg.pose_ukf.q_rotation == 0.5
    assert cfg.pose_ukf.q_translation == TrackerConfig().pose_ukf.q_translation


@pytest.mark.parametrize(("data", "match"), [
    ({"metod": "full"}, r"unknown field\(s\) \['metod'\]"),
    ({"method": "magic"}, "method"),
    ({"velocity_step_us": 1500}, "multiple of flow.window_us"),
    ({"velocity_step_us": 1.5}, "velocity_step_us"),
    ({"flow": {"roi_sise": 3}}, "roi_sise"),
    ({"flow": {"window_us": "fast"}}, "window_us"),
    ({"pose_ukf": {"q_rotation": "a lot"}}, "q_rotation"),
    ({"pose_ukf": {"gate": 3}}, "gate"),
    ({"velocity_kf": {"weighting": "yes"}}, "weighting"),
    ({"velocity_kf": {"normal_flow_std": -5}}, "normal_flow_std"),
    ({"frame_flow": {"algorithm": "raft"}}, "algorithm"),
    ({"ge": {"contrast": -1}}, "contrast"),
    ({"pose_rate_hz": 0}, "pose_rate_hz"),
    ({"depth": {"source": "lidar"}}, "depth.source"),
    ({"history_ms": 100}, "history_ms"),
    ({"use_flow_normal_flags": 1}, "use_flow_normal_flags"),
    ({"load": {"search_per_roi_window": -1}}, "search_per_roi_window"),
    ({"load": {"search_per_roi_window": 2.5}}, "search_per_roi_window"),
    ({"load": {"max_searched_per_step": -1}}, "max_searched_per_step"),
    ({"load": {"max_searched_per_step": "all"}}, "max_searched_per_step"),
])
def test_errors_name_the_field(data, match) -> None:
    with pytest.raises(ConfigError, match=match):
        TrackerConfig.from_dict(data)


def test_yaml_errors_name_the_file(tmp_path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"pose_latency_ms": -5.0}))
    with pytest.raises(ConfigError, match="bad.yaml.*pose_latency_ms"):
        TrackerConfig.from_yaml(path)
    path.write_text("method: [unclosed")
    with pytest.raises(ConfigError, match="bad.yaml"):
        TrackerConfig.from_yaml(path)
    path.write_text("- a list")
    with pytest.raises(ConfigError, match="mapping"):
        TrackerConfig.from_yaml(path)


def test_the_constructor_checks_types_as_from_dict_does() -> None:
    with pytest.raises(ConfigError, match="depth_fusion: icp: expected true or false"):
        TrackerConfig(depth_fusion={"icp": "false"})  # a truthy string must not turn ICP on
    with pytest.raises(ConfigError, match="velocity_kf: expected a mapping"):
        TrackerConfig(velocity_kf=5)
    with pytest.raises(ConfigError, match="pose_gate: must be a PoseGateConfig"):
        TrackerConfig(pose_gate=DepthConfig())
    cfg = TrackerConfig(velocity_kf={"flow_std": 12}, flow={"roi_size": 16}, pose_rate_hz=10)
    assert cfg.velocity_kf.flow_std == 12.0 and isinstance(cfg.velocity_kf.flow_std, float)
    assert cfg.velocity_kf.q_linear == TrackerConfig().velocity_kf.q_linear
    assert cfg.flow.roi_size == 16 and cfg.flow.window_us == TrackerConfig().flow.window_us
    assert cfg.pose_rate_hz == 10.0 and isinstance(cfg.pose_rate_hz, float)
    with pytest.raises(ConfigError, match="velocity_kf.*flw_std"):
        TrackerConfig(velocity_kf={"flw_std": 12})


@pytest.mark.parametrize(("data", "match"), [
    ({"flow_batch_steps": float("inf")}, "flow_batch_steps: expected an integer, got inf"),
    ({"flow_batch_steps": float("nan")}, "flow_batch_steps: expected an integer"),
    ({"flow": {"window_us": float("inf")}}, "flow.window_us: expected an integer"),
    ({"pose_rate_hz": 3e6}, "pose_rate_hz: .*one pose per velocity step"),
    ({"pose_rate_hz": "10"}, "pose_rate_hz: expected a number, got '10'"),  # quoted: a string
])
def test_non_finite_integers_runaway_rates_and_quoted_numbers_are_errors(data, match) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        TrackerConfig.from_dict(data)
    assert "tracker config: tracker config" not in str(info.value)


def test_scientific_notation_that_yaml_reads_as_a_string_is_a_number(tmp_path) -> None:
    path = tmp_path / "sci.yaml"
    path.write_text("pose_rate_hz: 1e1\nload: {max_searched_per_step: 2.5e3}\n"
                    "pose_ukf: {q_translation: 1e-2}\n")
    assert yaml.safe_load(path.read_text())["pose_rate_hz"] == "1e1"  # YAML 1.1's reading
    cfg = TrackerConfig.from_yaml(path)
    assert cfg.pose_rate_hz == 10.0 and cfg.load.max_searched_per_step == 2500
    assert cfg.pose_ukf.q_translation == 0.01


def test_a_device_this_torch_cannot_use_is_a_config_error() -> None:
    import numpy as np
    import torch

    from evtrack.camera import PinholeCamera
    from evtrack.tracking.tracker import Tracker

    cam = PinholeCamera(100.0, 100.0, 63.5, 47.5, 128, 96)
    cube = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])
    with pytest.raises(ConfigError, match="'foo' is not a torch device"):
        Tracker(TrackerConfig(device="foo"), camera=cam, mesh=cube)
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA device"):
            Tracker(TrackerConfig(device="cuda"), camera=cam, mesh=cube)


def test_a_misspelt_field_gets_the_nearest_name() -> None:
    with pytest.raises(ConfigError, match="'metod': did you mean 'method'"):
        TrackerConfig.from_dict({"metod": "full"})
    with pytest.raises(ConfigError, match="'flw_std': did you mean 'flow_std'"):
        TrackerConfig.from_dict({"velocity_kf": {"flw_std": 1.0}})
    with pytest.raises(ConfigError, match="'roi_sise': did you mean 'roi_size'"):
        TrackerConfig.from_dict({"flow": {"roi_sise": 3}})
    with pytest.raises(ConfigError, match=r"\['zzz'\]; known: \['appearance', 'blas_threads'"):
        TrackerConfig.from_dict({"zzz": 1})  # nothing close: the known names


def test_a_yaml_file_with_several_sections_gives_its_tracker_section(tmp_path) -> None:
    path = tmp_path / "all.yaml"
    path.write_text("sim: {duration: 1.0}\ntracker: {pose_rate_hz: 10.0}\n")
    assert TrackerConfig.from_yaml(path).pose_rate_hz == 10.0
    path.write_text("pose_latency_ms: 50.0\ntracker: {pose_rate_hz: 10.0}\n")
    with pytest.raises(ConfigError, match=r"\['pose_latency_ms'\] at the top level beside"):
        TrackerConfig.from_yaml(path)


def test_the_flat_keys_of_earlier_versions_load_with_a_warning_naming_the_new_key(tmp_path
                                                                                  ) -> None:
    path = tmp_path / "old.yaml"
    path.write_text("depth_source: model\nrealtime_load: 0.5\npose_depth_min_share: 0.7\n"
                    "load: {max_searched_per_step: 2000}\n")
    with pytest.warns(RenamedKeyWarning) as record:
        cfg = TrackerConfig.from_yaml(path)
    messages = sorted(str(w.message) for w in record)
    assert len(messages) == 3 and all(str(path) in m for m in messages)
    assert any("'depth_source' is renamed 'depth.source'" in m for m in messages)
    assert any("'realtime_load' is renamed 'load.realtime'" in m for m in messages)
    assert cfg.depth.source == "model" and cfg.load.realtime == 0.5
    assert cfg.load.max_searched_per_step == 2000  # the section's other keys kept
    assert cfg.pose_gate.depth_min_share == 0.7
    assert set(TrackerConfig.RENAMED_KEYS) >= {"depth_icp", "remeasure_on_pose",
                                                "pose_half_turn_axes", "max_events_per_step"}
    with pytest.raises(ConfigError, match="depth.source"):  # both the old and the new key
        TrackerConfig.from_dict({"depth_source": "model", "depth": {"source": "sensor"}})


def test_from_dict_lays_changes_over_a_base_section_by_section() -> None:
    base = TrackerConfig.from_dict({"pose_gate": {"depth_min_share": 0.7},
                                    "flow": {"roi_size": 16}})
    cfg = TrackerConfig.from_dict({"pose_gate": {"depth_align": False}}, base=base)
    assert cfg.pose_gate.depth_min_share == 0.7 and cfg.pose_gate.depth_align is False
    assert cfg.flow.roi_size == 16 and cfg.flow.window_us == 1000
    assert TrackerConfig.from_dict(None, base=base) == base


def test_every_section_reads_back_its_own_dict() -> None:
    cfg = TrackerConfig()
    for section in (cfg.pose_gate, cfg.depth, cfg.depth_fusion, cfg.load, cfg.remeasure,
                    cfg.frame_flow, cfg.ge):
        assert type(section).from_dict(section.to_dict()) == section
