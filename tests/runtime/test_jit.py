"""evtrack.runtime.jit: the optional numba wrapper and its start-up warm-up."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.runtime import jit


def test_njit_keeps_the_result():
    def add(a, b):
        return a + b

    assert jit.njit(add)(2, 3) == 5
    assert jit.njit(add)(np.arange(3), 1).tolist() == [1, 2, 3]


def test_warm_up_runs_once(monkeypatch):
    if not jit.available():
        pytest.skip("numba is not installed: warm_up does nothing")
    calls = []
    first = jit._first

    def counted(values):
        calls.append(len(values))
        return first(values)

    monkeypatch.setattr(jit, "_first", counted)
    monkeypatch.setattr(jit, "_warmed", False)
    jit.warm_up()
    jit.warm_up()
    assert calls == [1] and jit._warmed


def test_the_tracker_warms_up_when_made(monkeypatch):
    from evtrack.camera import PinholeCamera
    from evtrack.tracking import tracker as tracker_module

    calls = []
    monkeypatch.setattr(tracker_module, "warm_up", lambda: calls.append(1))
    cube = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])
    tracker_module.Tracker(camera=PinholeCamera(160.0, 160.0, 63.5, 47.5, 128, 96), mesh=cube)
    assert calls == [1]
