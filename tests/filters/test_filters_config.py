"""Filter configs: the shipped YAML equals the dataclass defaults; bad fields are named."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from evtrack.configs import from_dict
from evtrack.errors import ConfigError
from evtrack.filters import PoseTwistUKFConfig, PoseUKFConfig, VelocityKFConfig, load_filters_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "filters.yaml"


def test_shipped_yaml_equals_defaults() -> None:
    kf, ukf, cv = load_filters_config(CONFIGS)
    assert (kf, ukf, cv) == (VelocityKFConfig(), PoseUKFConfig(), PoseTwistUKFConfig())


def test_partial_yaml_and_types(tmp_path: Path) -> None:
    path = tmp_path / "f.yaml"
    path.write_text(
        "velocity_kf:\n  alpha: 0.8\n  laplace_scale: 20\npose_ukf:\n  gate_chi2: .inf\n"
        "  reinit_after: 3.0\n"
    )
    kf, ukf, cv = load_filters_config(path)
    assert (
        kf.alpha == 0.8 and kf.laplace_scale == 20.0 and kf.flow_std == VelocityKFConfig().flow_std
    )
    assert math.isinf(ukf.gate_chi2) and ukf.reinit_after == 3 and isinstance(ukf.reinit_after, int)
    assert cv == PoseTwistUKFConfig()


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("velocity_kf:\n  alpha: 1.5\n", "alpha"),
        ("velocity_kf:\n  flow_std: -1\n", "flow_std"),
        ("velocity_kf:\n  normal_flow_std: 0\n", "normal_flow_std"),
        ("velocity_kf:\n  normal_flow: 1\n", "normal_flow"),
        ("velocity_kf:\n  weighting_reference: median\n", "weighting_reference"),
        ("velocity_kf:\n  weighting_iterations: 1.5\n", "weighting_iterations"),
        ("velocity_kf:\n  bogus: 1\n", "bogus"),
        ("pose_ukf:\n  reinit_after: 0\n", "reinit_after"),
        ("pose_ukf:\n  gate_chi2: -3\n", "gate_chi2"),
        ("pose_twist_ukf:\n  alpha: 0\n", "alpha"),
        ("kalman: {}\n", "kalman"),
        ("- a list\n", "mapping"),
        ("velocity_kf: [1, 2]\n", "mapping"),
        ("velocity_kf:\n  alpha: [0.5\n", "cannot read"),
    ],
)
def test_bad_configs_name_the_file_and_field(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        load_filters_config(path)
    assert str(path) in str(info.value)


def test_missing_file_and_dict_source() -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_filters_config("/nonexistent/filters.yaml")
    cfg = from_dict(PoseUKFConfig, {"sigma_points": True}, "tracker.yaml: pose_ukf")
    assert cfg.sigma_points
    with pytest.raises(ConfigError, match="tracker.yaml: pose_ukf: unknown"):
        from_dict(PoseUKFConfig, {"sigmapoints": True}, "tracker.yaml: pose_ukf")
