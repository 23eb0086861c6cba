"""Motion sources by name (``TrackerConfig.method``): the built-in ones, found lazily, and any a
user registers with :func:`register_motion_source`."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from evtrack.tracking.motion.base import MotionSource

__all__ = ["METHODS", "method_names", "motion_source_class", "register_motion_source"]

_BUILT_IN = {
    "full": "evtrack.tracking.motion.events:EventMotion",
    "velocity": "evtrack.tracking.motion.events:VelocityOnlyMotion",
    "pose": "evtrack.tracking.motion.pose_only:PoseOnlyMotion",
    "frame-flow": "evtrack.tracking.baselines.frame_flow_motion:FrameFlowMotion",
    "ge": "evtrack.tracking.baselines.ge_motion:GEMotion",
}

METHODS = tuple(_BUILT_IN)
"""The built-in tracking methods (``TrackerConfig.method``), see :class:`evtrack.Tracker`."""

_registered: dict[str, type[MotionSource]] = {}


def register_motion_source(name: str, cls: type[MotionSource] | None = None):
    """Make ``cls`` (a :class:`~evtrack.tracking.motion.MotionSource` subclass) the motion
    source of ``TrackerConfig(method=name)``. Usable as a decorator
    (``@register_motion_source("mine")``). A built-in name cannot be taken.

    Raises:
        ValueError: ``name`` is a built-in method's.
        TypeError: ``cls`` is not a MotionSource subclass.
    """
    from evtrack.tracking.motion.base import MotionSource

    if name in _BUILT_IN:
        raise ValueError(f"motion source {name!r} is built in; register yours under another "
                         "name")

    def register(source: type[MotionSource]) -> type[MotionSource]:
        if not (isinstance(source, type) and issubclass(source, MotionSource)):
            raise TypeError(f"register_motion_source({name!r}): expected a MotionSource "
                            f"subclass, got {source!r}")
        _registered[name] = source
        return source

    return register if cls is None else register(cls)


def method_names() -> tuple[str, ...]:
    """Every method name ``TrackerConfig.method`` accepts: the built-in ones, then the
    registered ones."""
    return METHODS + tuple(_registered)


def motion_source_class(name: str) -> type[MotionSource]:
    """The motion source class of method ``name``.

    Raises:
        KeyError: no such method (the message lists the known ones).
    """
    if name in _registered:
        return _registered[name]
    if name not in _BUILT_IN:
        raise KeyError(f"unknown tracking method {name!r}; known: {', '.join(method_names())}")
    module, attr = _BUILT_IN[name].split(":")
    return getattr(importlib.import_module(module), attr)
