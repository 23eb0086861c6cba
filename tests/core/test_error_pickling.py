"""evtrack's errors cross process boundaries intact (``evaluate --jobs`` runs sequences in
worker processes, whose exceptions come back pickled): the type, the message and the fields
that name the file or config at fault."""

from __future__ import annotations

import pickle

import pytest

from evtrack.configs import FieldError
from evtrack.errors import ConfigError, EventFileError, EventsError, UnknownFormatError
from evtrack.models.weights import WeightsError
from evtrack.sim.errors import MeshFileError
from evtrack.tracking.config import TrackerConfig


@pytest.mark.parametrize("error", [
    EventFileError("events.h5", "truncated at event 12"),
    UnknownFormatError("capture.bin", "neither its extension nor its first bytes are known"),
    MeshFileError("object.glb", "has no faces"),
    WeightsError("net.pt", "not a weights file"),
    FieldError(TrackerConfig, "pose_rate_hz", "must be > 0, got -1"),
    ConfigError("tracker.yaml: unknown field 'x'"),
    EventsError("timestamps are not sorted"),
], ids=lambda e: type(e).__name__)
def test_errors_survive_pickling(error) -> None:
    copy = pickle.loads(pickle.dumps(error))
    assert type(copy) is type(error) and str(copy) == str(error)
    for name in ("path", "problem", "field", "owner"):
        assert getattr(copy, name, None) == getattr(error, name, None)
