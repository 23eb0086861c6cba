"""Shared fixtures: small simulated sequences (evtrack.sim) and cached tracker runs.

The fast sequence is 128x96 px, 0.6 s of the ``faster`` preset with a procedural box (median
pixel speed 150 px/s, i.e. 770 px/s at 640x480); contrast threshold 0.5 keeps it to ~32k events
so that a full tracker run takes about 4 s of CPU.
"""

from __future__ import annotations

import pytest
from robustness_scenes import knot_trajectory, simulate_sequence
from tracker_helpers import make_tracker, sim_config

from evtrack import Sequence
from evtrack.sim.engine import sequence_trajectory, simulate
from evtrack.sim.objects import procedural_object
from evtrack.sim.trajectory import static_trajectory


@pytest.fixture(scope="session")
def box():
    return procedural_object("box", 0)


@pytest.fixture(scope="session")
def fast_sequence(tmp_path_factory, box) -> Sequence:
    out = tmp_path_factory.mktemp("tracker") / "fast"
    simulate(box, sim_config(0.6, 3), out)
    return Sequence.load(out)


@pytest.fixture(scope="session")
def static_sequence(tmp_path_factory, box) -> Sequence:
    """The object at rest for 0.4 s (no events: the scene is static, the sensor noiseless)."""
    cfg = sim_config(0.4, 3)
    pose = sequence_trajectory(cfg, box).pose(0.3)
    out = tmp_path_factory.mktemp("tracker") / "static"
    simulate(box, cfg, out, trajectory=static_trajectory(pose, 0.5))
    return Sequence.load(out)


class RunCache:
    """Tracker runs shared between tests (each full run costs seconds)."""

    def __init__(self, seq: Sequence) -> None:
        self.seq = seq
        self.runs: dict[str, tuple] = {}

    def get(self, method: str, **config):
        if method not in self.runs:
            tracker, source = make_tracker(self.seq, method=method, **config)
            self.runs[method] = (tracker.track(self.seq), tracker, source)
        return self.runs[method]


@pytest.fixture(scope="session")
def runs(fast_sequence) -> RunCache:
    return RunCache(fast_sequence)


@pytest.fixture(params=["compiled", "numpy"])
def depth_form(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Runs a depth-lookup test with the compiled patch medians (numba) and with NumPy."""
    import evtrack.tracking.depth_sources as depth_sources

    if request.param == "compiled" and not depth_sources.numba_available():
        pytest.skip("numba is not installed")
    monkeypatch.setattr(depth_sources, "COMPILED", request.param == "compiled")
    return request.param


@pytest.fixture(scope="session")
def exit_sequence(tmp_path_factory, box):
    """The box crosses the image to the right, leaves it at ~0.37 s, waits outside, comes back
    from the right at ~0.8 s and slows down in the middle (z = 0.7 m)."""
    z = 0.7
    traj = knot_trajectory(
        [0.0, 0.3, 0.45, 0.7, 0.85, 1.1],
        [[-0.15, 0, z], [0.3, 0.0, z], [0.6, 0, z], [0.6, 0, z], [0.25, 0, z], [0.05, 0.02, z]],
        [[1.2, 0, 0], [1.5, 0, 0], [0, 0, 0], [0, 0, 0], [-1.5, 0, 0], [0, 0, 0]],
        rotvecs=[[0, 0, 0], [0.2, 0.3, 0.1], [0.3, 0.4, 0.1], [0.3, 0.4, 0.1], [0.2, 0.2, 0.0],
                 [0.1, 0.1, 0.0]],
        rotvec_rates=[[0.5, 0.5, 0.2], [0.8, 0.8, 0.2], [0, 0, 0], [0, 0, 0],
                      [-0.8, -0.8, -0.2], [0, 0, 0]])
    return simulate_sequence(box, traj, 1.1, tmp_path_factory.mktemp("robust") / "exit")
