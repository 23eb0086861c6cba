"""evtrack: fast 6-DoF object pose tracking with an event camera and an RGB-D camera.

Public API (reference: docs/api/)::

    import evtrack
    ev = evtrack.io.read_events("recording.h5")
    cam = evtrack.PinholeCamera(fx, fy, cx, cy, width, height)
    seq = evtrack.Sequence.load("sequence_folder")
"""

from __future__ import annotations

# first, before torch loads: sets OMP_WAIT_POLICY=PASSIVE unless set (see the module)
import evtrack.runtime.openmp_wait  # noqa: F401  # isort: skip
from evtrack import flow, geometry, io
from evtrack.camera import PinholeCamera
from evtrack.errors import (
    ConfigError,
    EventFileError,
    EventsError,
    EvtrackError,
    UnknownFormatError,
)
from evtrack.events import Events, EventsValidationReport, concatenate
from evtrack.sequence import Sequence
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.multi import MultiTracker, TrackedObject
from evtrack.tracking.tracker import Tracker, TrackerStats
from evtrack.tracking.trajectory import Trajectory

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "EventFileError",
    "Events",
    "EventsError",
    "EventsValidationReport",
    "EvtrackError",
    "MultiTracker",
    "PinholeCamera",
    "Sequence",
    "Tracker",
    "TrackerConfig",
    "TrackedObject",
    "TrackerStats",
    "Trajectory",
    "UnknownFormatError",
    "concatenate",
    "flow",
    "geometry",
    "io",
]
