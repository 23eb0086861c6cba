"""One loader for every configuration dataclass: YAML files and dicts in, checked dataclasses out.

A config class is a dataclass (usually deriving from :class:`Config`, which adds ``from_dict``,
``from_yaml`` and ``to_dict``); its type hints say what each field takes, and the same rules
apply to every config of the project:

- ``bool``: ``true``/``false`` only (not ``1``, not ``"yes"``).
- ``int``: an integer; ``5.0`` is taken as ``5``, ``5.5`` and ``true`` are errors.
- ``float``: any number (an integer becomes a float).
- ``int`` and ``float`` also take a string in scientific notation: YAML 1.1 (PyYAML) reads
  ``1e-3`` (no dot) as a string, so ``lr: 1e-3`` is ``0.001``. It is parsed, never evaluated;
  any other string (``"16"``) stays an error.
- ``str``: a string. ``Literal["a", "b"]``: one of those values. An ``enum.Enum``: one of its
  values (or member names). ``pathlib.Path``: a string or path.
- ``X | None``: ``null`` or an ``X``; other unions: the first member type that takes the value.
- ``tuple[X, Y]``: a list of exactly that many values; ``tuple[X, ...]`` and ``list[X]``: a list
  of any length (never a bare string). ``dict[str, X]``: a mapping. ``Any``: anything.
- A nested dataclass: a mapping of its fields (``null`` or an omitted section: its defaults,
  unless the field is optional). A class with a ``from_dict(data, source)`` of its own that does
  not derive from :class:`Config` is built with it.
- Unknown keys are errors naming the section and the key, with the nearest known key when
  one is close (``'metod': did you mean 'method'?``). Required fields (no default) must be
  given.

Every error is a :class:`~evtrack.errors.ConfigError` that starts with the source (the file, or
what the caller named) and the path of the field: ``run.yaml: events.threshold_on: expected a
number, got 'high'``.

**Ranges and units** are declared with :func:`setting` in place of ``field``; the checks run in
``Config.__post_init__`` (:func:`check_fields`), so they hold for configs built in code as well::

    @dataclass(frozen=True)
    class GateConfig(Config):
        '''Attributes:
            max_speed: fastest plausible motion, m/s.
            mode: ``"fast"`` or ``"exact"``.
        '''

        depth_check: bool = True
        max_speed: float = setting(2.0, gt=0, unit="m/s")
        mode: Literal["fast", "exact"] = "fast"

A bounded number must also be finite. Checks that involve several fields stay in the class's
``__post_init__`` (after ``super().__post_init__()``) and raise :class:`FieldError` naming the
field, or a plain :class:`ConfigError` about the whole section; the loader puts the file and the
section in front.

**Renamed keys**: a class lists ``old key -> new key`` in ``RENAMED_KEYS``; the new key may be a
dotted path into a nested section (``ClassVar``, so that the dataclass does not take it for a
field). A file that uses the old key still loads, with a :class:`RenamedKeyWarning` (a
``FutureWarning``) naming the new key; giving both is an error::

    @dataclass(frozen=True)
    class TrackerConfig(Config):
        RENAMED_KEYS: ClassVar[Mapping[str, str]] = {"pose_depth_check": "pose_gate.depth_check"}

        pose_gate: GateConfig = field(default_factory=GateConfig)

The conversion itself runs on a `cattrs <https://catt.rs>`_ converter (:data:`converter`) whose
hooks implement the rules above; another module can register hooks for its own field types on it.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import functools
import math
import os
import re
import types
import typing
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Literal, TypeVar

import cattrs
import yaml

from evtrack.errors import ConfigError

if TYPE_CHECKING:
    import torch

__all__ = [
    "Config",
    "ConfigError",
    "FieldError",
    "Range",
    "RenamedKeyWarning",
    "SCALAR_KINDS",
    "apply_overrides",
    "check_fields",
    "checked_device",
    "convert_value",
    "converter",
    "field_units",
    "from_dict",
    "move_renamed",
    "number_from_text",
    "read_yaml",
    "setting",
    "to_dict",
    "unknown_fields",
]

C = TypeVar("C")


class FieldError(ConfigError):
    """A bad value of one field, raised by a config class's own checks.

    Raised while building a config in code, it reads ``GateConfig.max_speed: must be > 0 m/s,
    got -1.0``; the loader replaces the class name by the file and the field's path
    (``tracker.yaml: pose_gate.max_speed: ...``).

    Args:
        owner: the config (or its class) whose field is at fault.
        name: the field; a dotted name points into a mapping field (``trainer.max_epochs``).
        problem: what is wrong, e.g. ``must be 0 < near < far, got (1.2, 0.4)``.
    """

    def __init__(self, owner: object, name: str, problem: str) -> None:
        self.owner: type = owner if isinstance(owner, type) else type(owner)
        self.field = name
        self.problem = problem
        super().__init__(f"{self.owner.__name__}.{name}: {problem}")

    def __reduce__(self) -> tuple:
        # rebuilt from its arguments, so that the error crosses process boundaries
        return type(self), (self.owner, self.field, self.problem)


class RenamedKeyWarning(FutureWarning):
    """A config used a key that has a new name (``RENAMED_KEYS`` of its class)."""


# ---------------------------------------------------------------------------- scalar rules
_SCIENTIFIC = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)[eE][+-]?\d+")
"""A number in scientific notation. YAML 1.1 (PyYAML) reads ``1e-3`` as a string (it wants
``1.0e-3``), so number fields also take such strings; a quoted plain number (``"16"``) stays
a string, and an error."""

SCALAR_KINDS: Mapping[type, str] = types.MappingProxyType(
    {bool: "true or false", int: "an integer", float: "a number", str: "a string"})
"""What each scalar field type takes, in words (as error messages say it)."""


def number_from_text(value: Any) -> Any:
    """``value`` as a float if it is a string in scientific notation (``"1e-3"``, which YAML
    1.1 reads as a string), else ``value`` unchanged. Parsed, never evaluated."""
    if isinstance(value, str) and _SCIENTIFIC.fullmatch(value.strip()):
        return float(value)
    return value


def _scalar(value: Any, kind: type) -> Any:
    """``value`` as ``kind`` (bool, int, float or str) by the rules of the module docstring;
    ``TypeError`` if it is not one."""
    if kind is bool:
        if isinstance(value, bool):
            return value
    elif kind is str:
        if isinstance(value, str):
            return value
    else:
        number = number_from_text(value)
        if isinstance(number, bool) or not isinstance(number, int | float):
            raise TypeError(kind)
        if kind is float:
            return float(number)
        if isinstance(number, int):
            return number
        if number.is_integer():
            return int(number)
    raise TypeError(kind)


# ---------------------------------------------------------------------------- where we are
_LOCATION: ContextVar[tuple[str, tuple[str | int, ...]]] = ContextVar(
    "config_location", default=("config", ()))
"""The source being loaded and the path of the value being converted in it."""


def _where(*extra: str | int) -> str:
    """``source: path.to[0].field`` of the value being converted (plus ``extra`` keys)."""
    source, path = _LOCATION.get()
    text = ""
    for key in (*path, *extra):
        text += f"[{key}]" if isinstance(key, int) else (f".{key}" if text else str(key))
    return f"{source}: {text}" if text else source


@contextmanager
def _at(key: str | int) -> Iterator[None]:
    source, path = _LOCATION.get()
    token = _LOCATION.set((source, (*path, key)))
    try:
        yield
    finally:
        _LOCATION.reset(token)


@contextmanager
def _loading(source: str) -> Iterator[None]:
    token = _LOCATION.set((source, ()))
    try:
        yield
    finally:
        _LOCATION.reset(token)


def _expected(what: str, value: Any) -> ConfigError:
    return ConfigError(f"{_where()}: expected {what}, got {value!r}")


# ---------------------------------------------------------------------------- ranges
@dataclasses.dataclass(frozen=True)
class Range:
    """Bounds of a number field (``None``: unbounded on that side), its unit, and a note that
    error messages add (``a confidence; 0: off``). A bounded value must be finite; a tuple's
    every element must be in range."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    unit: str | None = None
    note: str | None = None

    def text(self) -> str:
        """``> 0``, ``in [0, 1]``, ``in (0, 180] deg``, ..."""
        low = ("(", self.gt) if self.gt is not None else ("[", self.ge)
        high = (")", self.lt) if self.lt is not None else ("]", self.le)
        if low[1] is not None and high[1] is not None:
            text = f"in {low[0]}{low[1]:g}, {high[1]:g}{high[0]}"
        elif low[1] is not None:
            text = f"{'>' if low[0] == '(' else '>='} {low[1]:g}"
        else:
            text = f"{'<' if high[0] == ')' else '<='} {high[1]:g}"
        return f"{text} {self.unit}" if self.unit else text

    @functools.cached_property
    def _bounds(self) -> tuple[float, bool, float, bool]:
        """``(low, low is open, high, high is open)``; a missing bound is an open infinity, so
        that the comparisons alone also refuse infinities and NaN."""
        low, low_open = ((self.gt, True) if self.gt is not None
                         else (self.ge, False) if self.ge is not None else (-math.inf, True))
        high, high_open = ((self.lt, True) if self.lt is not None
                           else (self.le, False) if self.le is not None else (math.inf, True))
        return low, low_open, high, high_open

    def contains(self, value: float) -> bool:
        """Whether the number ``value`` is in range (and finite)."""
        low, low_open, high, high_open = self._bounds
        return ((value > low if low_open else value >= low)
                and (value < high if high_open else value <= high)
                and math.isfinite(value))

    def accepts(self, value: Any) -> bool:
        """Whether ``value`` is in range: a number, or each number of a tuple or list (other
        values pass: their type is the loader's business)."""
        if isinstance(value, tuple | list):
            return all(self.accepts(v) for v in value)
        if isinstance(value, bool) or not isinstance(value, int | float):
            return True
        return self.contains(value)

    def problem(self, value: Any) -> str:
        """``must be <range> (<note>), got <value>``."""
        note = f" ({self.note})" if self.note else ""
        return f"must be {self.text()}{note}, got {value!r}"


_RANGE = "evtrack.range"
_UNIT = "evtrack.unit"


def setting(default: Any = dataclasses.MISSING, *,
            default_factory: Callable[[], Any] | Any = dataclasses.MISSING,
            gt: float | None = None, ge: float | None = None,
            lt: float | None = None, le: float | None = None,
            unit: str | None = None, note: str | None = None) -> Any:
    """A dataclass field with a range and a unit: ``dataclasses.field`` plus the metadata that
    :func:`check_fields` reads.

    Args:
        default, default_factory: as for ``dataclasses.field``.
        gt, ge, lt, le: bounds (greater than, greater or equal, less than, less or equal).
        unit: the field's unit (``"m/s"``, ``"deg"``), shown in range errors; the class
            docstring states it as well.
        note: shown in range errors after the range, e.g. ``"0: off"``.
    """
    metadata: dict[str, Any] = {}
    if unit is not None:
        metadata[_UNIT] = unit
    if any(b is not None for b in (gt, ge, lt, le)):
        metadata[_RANGE] = Range(gt, ge, lt, le, unit, note)
    return dataclasses.field(default=default, default_factory=default_factory,
                             metadata=metadata)


def field_units(cls: type) -> dict[str, str]:
    """The units that the fields of the dataclass ``cls`` declare with :func:`setting`, by
    field name (``{"max_speed": "m/s"}``)."""
    return {f.name: f.metadata[_UNIT] for f in dataclasses.fields(cls) if _UNIT in f.metadata}


# ---------------------------------------------------------------------------- field checks
@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _literal_choices(tp: Any) -> tuple[Any, ...] | None:
    """The values of a ``Literal`` (also inside ``Optional``), else ``None``."""
    if typing.get_origin(tp) is Literal:
        return typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            if typing.get_origin(arg) is Literal:
                return typing.get_args(arg)
    return None


def _literal_match(value: Any, choices: tuple[Any, ...]) -> bool:
    return any(value == c and type(value) is type(c) for c in choices)


def _choices_problem(value: Any, choices: tuple[Any, ...]) -> str:
    return f"must be one of {list(choices)}, got {value!r}"


@functools.cache
def _field_rules(cls: type) -> tuple[tuple[str, tuple[Any, ...] | None, Range | None], ...]:
    hints = _type_hints(cls)
    rules = []
    for f in dataclasses.fields(cls):
        choices = _literal_choices(hints[f.name])
        limits = f.metadata.get(_RANGE)
        if choices is not None or limits is not None:
            rules.append((f.name, choices, limits))
    return tuple(rules)


def check_fields(config: Any) -> None:
    """Check ``config``'s ``Literal`` fields and the ranges declared with :func:`setting`
    (``None`` passes: whether a field may be ``None`` is its type's business).

    Raises:
        FieldError: naming the first field out of its choices or range.
    """
    for name, choices, limits in _field_rules(type(config)):
        value = getattr(config, name)
        if value is None:
            continue
        if choices is not None and not _literal_match(value, choices):
            raise FieldError(config, name, _choices_problem(value, choices))
        if limits is not None and not limits.accepts(value):
            raise FieldError(config, name, limits.problem(value))


def unknown_fields(unknown: Any, known: Any) -> str:
    """``unknown field(s) [...]`` with the nearest known name of each where one is close
    (``'metod': did you mean 'method'?``), else the list of the known names."""
    known = sorted(known)
    hints = []
    for name in sorted(unknown, key=str):
        close = difflib.get_close_matches(str(name), known, n=1, cutoff=0.7)
        if close:
            hints.append(f"{name!r}: did you mean {close[0]!r}?")
    text = f"unknown field(s) {sorted(unknown, key=str)}"
    if hints:
        return f"{text} ({'; '.join(hints)})"
    return f"{text}; known: {known}"


# ---------------------------------------------------------------------------- renamed keys
@functools.cache
def _renames(cls: type) -> Mapping[str, str]:
    """``cls.RENAMED_KEYS``, each new key checked to name a field (through nested sections)."""
    renames = dict(getattr(cls, "RENAMED_KEYS", None) or {})
    for old, new in renames.items():
        owner = cls
        for key in new.split("."):
            hints = _type_hints(owner) if dataclasses.is_dataclass(owner) else {}
            if key not in hints:
                raise TypeError(f"{cls.__name__}.RENAMED_KEYS: {old!r} -> {new!r}: "
                                f"{owner.__name__} has no field {key!r}")
            owner = _dataclass_in(hints[key])
    return renames


def _dataclass_in(tp: Any) -> Any:
    """The dataclass of a field typed ``D`` or ``D | None`` (else ``tp``)."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        found = [a for a in typing.get_args(tp) if dataclasses.is_dataclass(a)]
        return found[0] if len(found) == 1 else tp
    return tp


def _move_renamed(cls: type, data: Mapping[str, Any]) -> Mapping[str, Any]:
    """``data`` with each old key of ``cls`` moved to its new place, with a warning."""
    renames = _renames(cls)
    if not renames or renames.keys().isdisjoint(data):
        return data
    out = dict(data)
    for old, new in renames.items():
        if old not in out:
            continue
        value = out.pop(old)
        *sections, last = new.split(".")
        node = out
        for depth, key in enumerate(sections):
            child = node.get(key)
            if child is not None and not isinstance(child, Mapping):
                path = ".".join(sections[:depth + 1])
                raise ConfigError(f"{_where()}: {old!r} is now {new!r}, but {path!r} is not a "
                                  f"mapping")
            node[key] = dict(child or {})
            node = node[key]
        if last in node:
            raise ConfigError(f"{_where()}: {old!r} and {new!r} are both given, but {old!r} is "
                              f"the old name of {new!r}: keep only {new!r}")
        node[last] = value
        warnings.warn(f"{_where()}: {old!r} is renamed {new!r}; write {new!r} (the old name "
                      f"will stop being read)", RenamedKeyWarning, stacklevel=2)
    return out


# ---------------------------------------------------------------------------- structure hooks
def _structure_scalar(value: Any, kind: type) -> Any:
    try:
        return _scalar(value, kind)
    except TypeError:
        raise _expected(SCALAR_KINDS[kind], value) from None


def _structure_any(value: Any, _: Any) -> Any:
    return value


def _structure_none(value: Any, _: Any) -> None:
    if value is not None:
        raise _expected("null", value)
    return None


def _structure_union(value: Any, tp: Any) -> Any:
    options = typing.get_args(tp)
    if value is None:
        if type(None) in options:
            return None
        raise ConfigError(f"{_where()}: must not be null")
    errors = []
    for option in options:
        if option is type(None):
            continue
        try:
            return converter.structure(value, option)
        except ConfigError as exc:
            errors.append(exc)
    if len(errors) == 1:
        raise errors[0]
    raise ConfigError(f"{_where()}: expected {_type_name(tp)}, got {value!r}")


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if tp in SCALAR_KINDS:
        return SCALAR_KINDS[tp]
    if tp is type(None):
        return "null"
    if typing.get_origin(tp) in (tuple, list) or tp in (tuple, list):
        return "a list"
    if dataclasses.is_dataclass(tp) or typing.get_origin(tp) is dict or tp is dict:
        return "a mapping"
    return getattr(tp, "__name__", repr(tp))


def _structure_literal(value: Any, tp: Any) -> Any:
    choices = typing.get_args(tp)
    if not _literal_match(value, choices):
        raise ConfigError(f"{_where()}: {_choices_problem(value, choices)}")
    return value


def _structure_enum(value: Any, tp: type[enum.Enum]) -> Any:
    for member in tp:
        if value is member or _literal_match(value, (member.value,)) or value == member.name:
            return member
    raise ConfigError(f"{_where()}: {_choices_problem(value, [m.value for m in tp])}")


def _structure_path(value: Any, _: Any) -> Path:
    if isinstance(value, str | os.PathLike):
        return Path(value)
    raise _expected("a path (a string)", value)


def _is_list(value: Any) -> bool:
    return isinstance(value, Sequence) and not isinstance(value, str | bytes)


def _items(values: Sequence[Any], kinds: Sequence[Any]) -> Iterator[Any]:
    for i, (value, kind) in enumerate(zip(values, kinds, strict=True)):
        with _at(i):
            yield converter.structure(value, kind)


def _structure_tuple(value: Any, tp: Any) -> tuple[Any, ...]:
    if not _is_list(value):
        raise _expected("a list", value)
    args = typing.get_args(tp)
    if not args:
        return tuple(value)
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(_items(value, [args[0]] * len(value)))
    if len(value) != len(args):
        raise _expected(f"a list of {len(args)} values", value)
    return tuple(_items(value, args))


def _structure_list(value: Any, tp: Any) -> list[Any]:
    if not _is_list(value):
        raise _expected("a list", value)
    args = typing.get_args(tp)
    return list(_items(value, [args[0] if args else Any] * len(value)))


def _structure_mapping(value: Any, tp: Any) -> dict[Any, Any]:
    if not isinstance(value, Mapping):
        raise _expected("a mapping", value)
    args = typing.get_args(tp)
    kind = args[1] if len(args) == 2 else Any
    out = {}
    for key, item in value.items():
        with _at(str(key)):
            out[key] = converter.structure(item, kind)
    return out


def _structure_dataclass(data: Any, cls: type[C]) -> C:
    """``cls`` from a mapping of its fields (``None``: the defaults)."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{_where()}: expected a mapping, got {type(data).__name__}")
    data = _move_renamed(cls, data)
    init_fields = [f for f in dataclasses.fields(cls) if f.init]  # type: ignore[arg-type]
    unknown = set(data) - {f.name for f in init_fields}
    if unknown:
        raise ConfigError(f"{_where()}: {unknown_fields(unknown, [f.name for f in init_fields])}")
    missing = [f.name for f in init_fields if f.name not in data
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"{_where()}: missing required field(s) {missing}")
    hints = _type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        with _at(name):
            kwargs[name] = converter.structure(value, hints[name])
    return _construct(cls, kwargs)


def _construct(cls: type[C], kwargs: dict[str, Any]) -> C:
    """``cls(**kwargs)``; the errors of its checks get the source and the path in front."""
    try:
        return cls(**kwargs)
    except FieldError as exc:
        if exc.owner is cls:
            raise ConfigError(f"{_where(*exc.field.split('.'))}: {exc.problem}") from None
        raise ConfigError(f"{_where()}: {exc}") from None
    except ConfigError as exc:
        raise ConfigError(f"{_where()}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{_where()}: {exc}") from exc


def _structure_own_loader(data: Any, cls: Any) -> Any:
    """A class with a ``from_dict(data, source)`` of its own (not a :class:`Config`)."""
    return cls.from_dict(data, _where())


def _has_own_loader(tp: Any) -> bool:
    return (isinstance(tp, type) and not issubclass(tp, Config)
            and callable(getattr(tp, "from_dict", None)))


def _has_own_dict(tp: Any) -> bool:
    return (isinstance(tp, type) and not issubclass(tp, Config)
            and callable(getattr(tp, "to_dict", None)))


def _unsupported(tp: Any) -> Callable[[Any, Any], Any]:
    def hook(value: Any, _: Any) -> Any:
        raise TypeError(f"{_where()}: no config rule for the field type {tp!r}")
    return hook


def _origin_in(*origins: Any) -> Callable[[Any], bool]:
    return lambda tp: tp in origins or typing.get_origin(tp) in origins


def _make_converter() -> cattrs.Converter:
    conv = cattrs.Converter(unstruct_collection_overrides={tuple: list},
                            detailed_validation=False, structure_fallback_factory=_unsupported)
    for kind in SCALAR_KINDS:
        conv.register_structure_hook(kind, _structure_scalar)
    conv.register_structure_hook(Path, _structure_path)
    conv.register_unstructure_hook(Path, str)
    conv.register_structure_hook(enum.Enum, _structure_enum)
    conv.register_structure_hook(type(None), _structure_none)
    # predicates: a later registration takes precedence
    conv.register_structure_hook_func(dataclasses.is_dataclass, _structure_dataclass)
    conv.register_structure_hook_func(_has_own_loader, _structure_own_loader)
    conv.register_unstructure_hook_func(_has_own_dict, lambda obj: obj.to_dict())
    conv.register_structure_hook_func(_origin_in(tuple), _structure_tuple)
    conv.register_structure_hook_func(_origin_in(list, Sequence), _structure_list)
    conv.register_structure_hook_func(_origin_in(dict, Mapping), _structure_mapping)
    conv.register_structure_hook_func(lambda tp: typing.get_origin(tp) is Literal,
                                      _structure_literal)
    conv.register_structure_hook_func(
        lambda tp: typing.get_origin(tp) in (typing.Union, types.UnionType), _structure_union)
    conv.register_structure_hook_func(lambda tp: tp is Any, _structure_any)
    return conv


converter: cattrs.Converter = _make_converter()
"""The converter that applies the rules of the module docstring (structure: value -> field
type; unstructure: config -> plain YAML-safe data)."""


# ---------------------------------------------------------------------------- public API
def from_dict(cls: type[C], data: Mapping[str, Any] | None, source: str = "config") -> C:
    """Build the config dataclass ``cls`` from nested mappings (``None``: its defaults).

    Args:
        cls: a dataclass.
        data: its fields, as read from YAML.
        source: what the data came from (a file name, ``record.decode``); errors start with it.

    Raises:
        ConfigError: naming ``source``, the path of the field and the problem.
    """
    with _loading(source):
        return converter.structure(data, cls)


def move_renamed(cls: type, data: Mapping[str, Any], source: str) -> Mapping[str, Any]:
    """``data`` with each old key of ``cls.RENAMED_KEYS`` moved to its new place (a
    :class:`RenamedKeyWarning` each, naming ``source``; both given: an error), for a caller
    that merges ``data`` into other data before loading it."""
    with _loading(source):
        return _move_renamed(cls, data)


def convert_value(value: Any, tp: Any, where: str) -> Any:
    """One value converted to the type ``tp`` by the loader's rules (a CLI option, a setting
    given as ``KEY=VALUE``).

    Raises:
        ConfigError: starting with ``where``.
    """
    with _loading(where):
        return converter.structure(value, tp)


def to_dict(config: Any) -> dict[str, Any]:
    """``config`` as plain nested data (YAML-safe: tuples become lists, paths strings, enums
    their values), in field order; :func:`from_dict` reads it back to an equal config."""
    return converter.unstructure(config)


def read_yaml(path: str | Path) -> dict[str, Any]:
    """The mapping at the top of the YAML file ``path`` (``yaml.safe_load``, never evaluated;
    an empty file is ``{}``).

    Raises:
        ConfigError: naming the file: not found, unreadable, invalid YAML, or not a mapping.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the config file: {exc}") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {exc}") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections, got "
                          f"{type(data).__name__}")
    return data


def apply_overrides(data: Mapping[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """A copy of the nested ``data`` with ``"a.b.c=value"`` overrides applied (each value
    parsed as YAML, never evaluated); ``data`` is not changed.

    Raises:
        ConfigError: naming the override: no ``=``, an empty key, invalid YAML, or a path
            through a value that is not a section.
    """
    import copy

    out = copy.deepcopy(dict(data))
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.field=value")
        key, raw = item.split("=", 1)
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"override {item!r}: empty field name")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {item!r}: value is not valid YAML: {exc}") from exc
        node = out
        for p in parts[:-1]:
            child = node.setdefault(p, {})
            if not isinstance(child, dict):
                raise ConfigError(f"override {item!r}: {p!r} is not a section")
            node = child
        node[parts[-1]] = value
    return out


class Config:
    """Base of the config dataclasses: loading, saving, and the field checks.

    A subclass is a dataclass; it may declare ``RENAMED_KEYS`` (see the module docstring).
    Its own ``__post_init__``, if any, calls ``super().__post_init__()`` first.
    """

    RENAMED_KEYS: ClassVar[Mapping[str, str]] = types.MappingProxyType({})
    """Old key -> new key (a dotted path for a key that moved into a nested section)."""

    def __post_init__(self) -> None:
        check_fields(self)

    @classmethod
    def from_dict(cls: type[C], data: Mapping[str, Any] | None,
                  source: str = "config") -> C:
        """Build from nested mappings (:func:`from_dict`); errors name ``source`` and the field."""
        return from_dict(cls, data, source)

    @classmethod
    def from_yaml(cls: type[C], path: str | Path, overrides: Sequence[str] = ()) -> C:
        """Load the YAML file ``path``, with ``section.field=value`` overrides applied."""
        data = apply_overrides(read_yaml(path), overrides) if overrides else read_yaml(path)
        return from_dict(cls, data, str(path))

    def to_dict(self) -> dict[str, Any]:
        """Plain nested data (YAML-safe); :meth:`from_dict` reads it back to an equal config."""
        return to_dict(self)

    def to_yaml(self, path: str | Path) -> None:
        """Write :meth:`to_dict` to ``path`` as YAML (atomically)."""
        from evtrack.utils import atomic_write_text

        atomic_write_text(path, yaml.safe_dump(self.to_dict(), sort_keys=False))


def checked_device(device: Any, where: str) -> torch.device:
    """``device`` as a ``torch.device`` that this torch can use.

    Raises:
        ConfigError: naming ``where``: not a device name, or CUDA asked for where this torch
            has none (or not that many GPUs).
    """
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ConfigError(f"{where}: {device!r} is not a torch device (cpu, cuda, cuda:1, "
                          f"...)") from exc
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"{where}: {device!r}, but this torch has no CUDA device (install "
                              "a CUDA build of torch, or use cpu)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"{where}: {device!r}, but only {torch.cuda.device_count()} "
                              "CUDA device(s) are visible")
    return dev
