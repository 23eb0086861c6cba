"""Exceptions raised by evtrack.

Every error names the file or field at fault and says what is wrong, so that a user can act on
it without reading the source.
"""

from __future__ import annotations

__all__ = [
    "EvtrackError",
    "EventsError",
    "EventFileError",
    "UnknownFormatError",
    "ConfigError",
]


class EvtrackError(Exception):
    """Base class of every error evtrack raises on purpose."""


class EventsError(EvtrackError, ValueError):
    """Events that break the container's invariants (unsorted, outside the sensor, bad polarity)."""


class EventFileError(EvtrackError, OSError):
    """An event or sequence file that cannot be read: truncated, corrupt or inconsistent."""

    def __init__(self, path: object, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self) -> tuple:
        # rebuilt from its arguments (the default would pass the message as ``path``), so
        # that the error crosses process boundaries (evaluate --jobs)
        return type(self), (self.path, self.problem)


class UnknownFormatError(EventFileError):
    """A file whose format is recognised neither by its extension nor by its first bytes."""


class ConfigError(EvtrackError, ValueError):
    """A configuration (YAML file or dict) with a missing, unknown or invalid field."""
