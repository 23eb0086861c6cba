"""Fixtures of the filter tests: counting the calls of the single-track backends."""

from __future__ import annotations

import pytest

from evtrack.filters.backends import single_track_backends

_COUNTED = ("velocity_predict", "velocity_update", "velocity_run", "pose_predict",
            "pose_predict_run", "pose_update")


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> dict[str, int]:
    """Counts the calls of every registered single-track backend's steps, as
    ``"<backend>.<step>"``."""
    counts: dict[str, int] = {}
    for backend in single_track_backends():
        for name in _COUNTED:
            original = getattr(backend, name)
            key = f"{backend.name}.{name}"

            def counted(*args: object, _f=original, _k=key) -> object:  # noqa: ANN001
                counts[_k] = counts.get(_k, 0) + 1
                return _f(*args)

            monkeypatch.setattr(backend, name, counted)
    return counts
