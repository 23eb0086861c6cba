"""The config loader (evtrack.configs): types, nesting, ranges, unknown and renamed keys."""

from __future__ import annotations

import enum
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import pytest

from evtrack.configs import (
    Config,
    FieldError,
    RenamedKeyWarning,
    apply_overrides,
    convert_value,
    field_units,
    from_dict,
    read_yaml,
    setting,
    to_dict,
)
from evtrack.errors import ConfigError


class Mode(enum.Enum):
    FAST = "fast"
    EXACT = "exact"


@dataclass(frozen=True)
class Gate(Config):
    depth_check: bool = True
    max_speed: float = setting(2.0, gt=0, unit="m/s")
    min_points: int = setting(4, ge=4, note="PnP needs 4")
    window: tuple[float, float] = (0.1, 0.9)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.window[0] < self.window[1]:
            raise FieldError(self, "window", f"must be increasing, got {self.window}")


@dataclass(frozen=True)
class Tracker(Config):
    RENAMED_KEYS: ClassVar[Mapping[str, str]] = {
        "pose_depth_check": "gate.depth_check",
        "speed": "gate.max_speed",
        "label": "name",
    }

    name: str
    rate_hz: float = setting(100.0, gt=0, le=1000, unit="Hz")
    count: int = 3
    scale: float | None = None
    kinds: tuple[str, ...] = ("box",)
    method: Literal["lm", "none"] = "lm"
    mode: Mode = Mode.FAST
    path: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    gate: Gate = field(default_factory=Gate)
    spare: Gate | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.scale is not None and self.count > 10:
            raise ConfigError("a scale needs count <= 10")


@dataclass
class Plain:
    a: int = 1


class Custom:
    """Not a Config: built by its own ``from_dict``, saved by its own ``to_dict``."""

    def __init__(self, value: int) -> None:
        self.value = value

    @classmethod
    def from_dict(cls, data: Any, source: str) -> Custom:
        if not isinstance(data, int):
            raise ConfigError(f"{source}: not an int")
        return cls(data)

    def to_dict(self) -> int:
        return self.value


@dataclass
class Outer:
    plain: Plain = field(default_factory=Plain)
    custom: Custom | None = None


def load(data: Any, source: str = "t.yaml") -> Tracker:
    return Tracker.from_dict(data, source)


def error(data: Any) -> str:
    with pytest.raises(ConfigError) as info:
        load(data)
    return str(info.value)


def test_types_are_converted_by_one_set_of_rules():
    cfg = load({"name": "x", "rate_hz": 50, "count": 7.0, "scale": 2, "kinds": ["can", "box"],
                "method": "none", "mode": "exact", "path": "a/b.yaml", "extra": {"k": [1]}})
    assert cfg.rate_hz == 50.0 and isinstance(cfg.rate_hz, float)
    assert cfg.count == 7 and isinstance(cfg.count, int)
    assert cfg.scale == 2.0 and isinstance(cfg.scale, float)
    assert cfg.kinds == ("can", "box") and cfg.method == "none" and cfg.mode is Mode.EXACT
    assert cfg.path == Path("a/b.yaml") and cfg.extra == {"k": [1]}


@pytest.mark.parametrize("data, message", [
    ({"count": 2.5}, "t.yaml: count: expected an integer, got 2.5"),
    ({"count": True}, "t.yaml: count: expected an integer, got True"),
    ({"rate_hz": "fast"}, "t.yaml: rate_hz: expected a number, got 'fast'"),
    ({"rate_hz": "16"}, "t.yaml: rate_hz: expected a number, got '16'"),
    ({"name": 5}, "t.yaml: name: expected a string, got 5"),
    ({"gate": {"depth_check": "yes"}},
     "t.yaml: gate.depth_check: expected true or false, got 'yes'"),
    ({"kinds": "box"}, "t.yaml: kinds: expected a list, got 'box'"),
    ({"kinds": ["box", 3]}, "t.yaml: kinds[1]: expected a string, got 3"),
    ({"gate": {"window": [0.1]}}, "t.yaml: gate.window: expected a list of 2 values, got [0.1]"),
    ({"method": "gn"}, "t.yaml: method: must be one of ['lm', 'none'], got 'gn'"),
    ({"mode": "slow"}, "t.yaml: mode: must be one of ['fast', 'exact'], got 'slow'"),
    ({"path": 3}, "t.yaml: path: expected a path (a string), got 3"),
    ({"extra": [1]}, "t.yaml: extra: expected a mapping, got [1]"),
    ({"gate": 5}, "t.yaml: gate: expected a mapping, got int"),
    ({"name": None}, "t.yaml: name: expected a string, got None"),
    ({"scale": "big"}, "t.yaml: scale: expected a number, got 'big'"),
])
def test_type_errors_name_the_file_and_the_field(data, message):
    assert error({"name": "x", **data}) == message


def test_optional_fields_and_nested_dataclasses():
    cfg = load({"name": "x", "scale": None, "spare": {"max_speed": 3}, "gate": None})
    assert cfg.scale is None and cfg.spare == Gate(max_speed=3.0) and cfg.gate == Gate()
    assert load({"name": "x", "spare": None}).spare is None
    assert load({"name": "x", "gate": {"window": [0, 1]}}).gate.window == (0.0, 1.0)


def test_scientific_notation_strings_are_numbers(tmp_path):
    path = tmp_path / "sci.yaml"
    path.write_text("name: x\nrate_hz: 1e2\ncount: 2e1\ngate: {max_speed: 5E-1}\n")
    data = read_yaml(path)
    assert data["rate_hz"] == "1e2"  # YAML 1.1 reads it as a string
    cfg = Tracker.from_yaml(path)
    assert cfg.rate_hz == 100.0 and cfg.count == 20 and isinstance(cfg.count, int)
    assert cfg.gate.max_speed == 0.5
    assert convert_value("-2.5e-3", float, "--step") == -0.0025
    with pytest.raises(ConfigError, match="^--step: expected an integer, got '1.5e0'"):
        convert_value("1.5e0", int, "--step")


def test_unknown_keys_name_the_file_the_section_and_the_nearest_key():
    assert error({"name": "x", "rate_hx": 5}) == (
        "t.yaml: unknown field(s) ['rate_hx'] ('rate_hx': did you mean 'rate_hz'?)")
    message = error({"name": "x", "gate": {"max_sped": 1, "zzz": 2}})
    assert message.startswith("t.yaml: gate: unknown field(s) ['max_sped', 'zzz'] (")
    assert "'max_sped': did you mean 'max_speed'?" in message
    assert error({"name": "x", "gate": {"zzz": 2}}) == (
        "t.yaml: gate: unknown field(s) ['zzz']; known: ['depth_check', 'max_speed', "
        "'min_points', 'window']")


def test_missing_required_field():
    assert error({"count": 1}) == "t.yaml: missing required field(s) ['name']"


def test_values_out_of_range():
    assert error({"name": "x", "rate_hz": 0}) == "t.yaml: rate_hz: must be in (0, 1000] Hz, got 0.0"
    assert error({"name": "x", "rate_hz": float("inf")}).startswith("t.yaml: rate_hz: must be")
    assert error({"name": "x", "gate": {"min_points": 3}}) == (
        "t.yaml: gate.min_points: must be >= 4 (PnP needs 4), got 3")
    assert error({"name": "x", "gate": {"window": [2, 1]}}) == (
        "t.yaml: gate.window: must be increasing, got (2.0, 1.0)")
    assert error({"name": "x", "scale": 1, "count": 11}) == "t.yaml: a scale needs count <= 10"
    with pytest.raises(FieldError, match=r"^Gate.max_speed: must be > 0 m/s, got -1$") as info:
        Gate(max_speed=-1)
    assert info.value.field == "max_speed" and info.value.owner is Gate
    with pytest.raises(FieldError, match=r"^Tracker.method: must be one of \['lm', 'none'\]"):
        Tracker("x", method="gn")  # type: ignore[arg-type]


def test_units_are_declared_with_the_range():
    assert field_units(Gate) == {"max_speed": "m/s"}
    assert field_units(Tracker) == {"rate_hz": "Hz"}


def test_renamed_keys_warn_with_the_new_key():
    with pytest.warns(RenamedKeyWarning, match="'pose_depth_check' is renamed "
                                               "'gate.depth_check'; write 'gate.depth_check'"):
        cfg = load({"name": "x", "pose_depth_check": False, "gate": {"min_points": 5}})
    assert cfg.gate == Gate(depth_check=False, min_points=5)
    assert issubclass(RenamedKeyWarning, FutureWarning)
    with pytest.warns(RenamedKeyWarning, match="t.yaml: 'label' is renamed 'name'"):
        assert load({"label": "y"}).name == "y"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RenamedKeyWarning)
        assert load({"name": "x", "speed": 4}).gate.max_speed == 4.0
        with pytest.raises(ConfigError, match=r"^t.yaml: gate.max_speed: must be > 0"):
            load({"name": "x", "speed": -4})


def test_renamed_key_given_with_its_new_name_is_an_error():
    with pytest.raises(ConfigError, match=r"^t.yaml: 'pose_depth_check' and 'gate.depth_check' "
                                          r"are both given.*keep only 'gate.depth_check'"):
        load({"name": "x", "pose_depth_check": False, "gate": {"depth_check": True}})
    with pytest.raises(ConfigError, match="'label' and 'name' are both given"):
        load({"name": "x", "label": "y"})
    with pytest.raises(ConfigError, match="'gate' is not a mapping"):
        load({"name": "x", "pose_depth_check": False, "gate": 3})


def test_renames_must_point_at_fields():
    @dataclass
    class Broken(Config):
        RENAMED_KEYS: ClassVar[Mapping[str, str]] = {"old": "gate.nothing"}

        gate: Gate = field(default_factory=Gate)

    with pytest.raises(TypeError, match="Gate has no field 'nothing'"):
        from_dict(Broken, {"old": 1})


def test_round_trip_dict_config_dict(tmp_path):
    cfg = load({"name": "x", "scale": 0.5, "kinds": ["a", "b"], "mode": "exact",
                "path": "p/q", "extra": {"n": 1}, "spare": {}})
    data = cfg.to_dict()
    assert data == {"name": "x", "rate_hz": 100.0, "count": 3, "scale": 0.5, "kinds": ["a", "b"],
                    "method": "lm", "mode": "exact", "path": "p/q", "extra": {"n": 1},
                    "gate": {"depth_check": True, "max_speed": 2.0, "min_points": 4,
                             "window": [0.1, 0.9]},
                    "spare": {"depth_check": True, "max_speed": 2.0, "min_points": 4,
                              "window": [0.1, 0.9]}}
    assert to_dict(cfg) == data and load(data) == cfg
    cfg.to_yaml(tmp_path / "cfg.yaml")
    assert Tracker.from_yaml(tmp_path / "cfg.yaml") == cfg


def test_plain_dataclasses_and_classes_with_their_own_loader():
    outer = from_dict(Outer, {"plain": {"a": "3e0"}, "custom": 4}, "o.yaml")
    assert outer.plain == Plain(3) and outer.custom.value == 4
    assert to_dict(outer) == {"plain": {"a": 3}, "custom": 4}
    with pytest.raises(ConfigError, match="^o.yaml: custom: not an int$"):
        from_dict(Outer, {"custom": "x"}, "o.yaml")


def test_yaml_files_and_overrides(tmp_path):
    with pytest.raises(ConfigError, match="none.yaml: config file not found"):
        Tracker.from_yaml(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [x,\n")
    with pytest.raises(ConfigError, match="bad.yaml: invalid YAML"):
        Tracker.from_yaml(bad)
    bad.write_text("- a list\n")
    with pytest.raises(ConfigError, match="bad.yaml: the top level must be a mapping"):
        Tracker.from_yaml(bad)
    good = tmp_path / "good.yaml"
    good.write_text("name: x\ngate:\n  max_speed: 1.0\n")
    cfg = Tracker.from_yaml(good, ["gate.max_speed=3", "count=4"])
    assert cfg.gate.max_speed == 3.0 and cfg.count == 4
    with pytest.raises(ConfigError, match=r"good.yaml: gate.max_speed: must be > 0"):
        Tracker.from_yaml(good, ["gate.max_speed=-1"])
    with pytest.raises(ConfigError, match="must look like section.field=value"):
        apply_overrides({}, ["count"])
    with pytest.raises(ConfigError, match="'name' is not a section"):
        apply_overrides({"name": "x"}, ["name.first=y"])
