"""The tracker stage: events, frames and poses in, the object's pose and twist out.

The package's modules follow the data flow (see ``docs/architecture.md``); the public names
are re-exported here and from :mod:`evtrack`.
"""

from __future__ import annotations

from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.tracker import Tracker, TrackerStats
from evtrack.tracking.trajectory import Trajectory

__all__ = ["Tracker", "TrackerConfig", "TrackerStats", "Trajectory"]
