"""The README's Python example runs as written: the tracker on a recorded sequence, the live
loop, and the ONNX export, on a short simulated sequence of the demo object."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
PLACEHOLDER = '"my_sequence"'


def _first_python_block(text: str) -> str:
    match = re.search(r"^```python\n(.*?)^```", text, re.MULTILINE | re.DOTALL)
    assert match, "README.md has no ```python block"
    return match.group(1)


@pytest.fixture(scope="module")
def demo_sequence(tmp_path_factory) -> Path:
    """0.3 s of the coded box (the object the shipped demo network knows) at 160x120."""
    from evtrack.sim.config import EventConfig, GroundTruthConfig, SimConfig, TrajectoryConfig
    from evtrack.sim.engine import simulate
    from evtrack.sim.objects import procedural_object

    cfg = SimConfig(duration=0.3, seed=0, trajectory=TrajectoryConfig(preset="faster"),
                    events=EventConfig(threshold_on=0.5, threshold_off=0.5),
                    ground_truth=GroundTruthConfig(event_flow=False))
    cfg = dataclasses.replace(cfg, camera=cfg.camera.resized(160, 120))
    out = tmp_path_factory.mktemp("readme") / "my_sequence"
    simulate(procedural_object("coded_box", 0), cfg, out)
    return out


def _camera_driver(folder: Path):
    """What a live application would hand the tracker: the events up to each frame time,
    then that time's RGB and depth frames (``None`` where the camera gave only one)."""
    from evtrack import Sequence

    def driver():
        seq = Sequence.load(folder)
        events = seq.events
        rgb_index = {t: i for i, t in enumerate(seq.rgb_times_us.tolist())}
        depth_index = {t: i for i, t in enumerate(seq.depth_times_us.tolist())}
        t_prev = events.t_start
        for t in sorted(set(rgb_index) | set(depth_index)):
            yield (t, events.between(t_prev, t),
                   seq.rgb(rgb_index[t]) if t in rgb_index else None,
                   seq.depth(depth_index[t]) if t in depth_index else None)
            t_prev = t

    return driver


@pytest.mark.slow
def test_readme_python_example_runs(demo_sequence: Path, tmp_path: Path, monkeypatch) -> None:
    code = _first_python_block((ROOT / "README.md").read_text(encoding="utf-8"))
    assert PLACEHOLDER in code, f"the README example no longer loads {PLACEHOLDER}"
    code = code.replace(PLACEHOLDER, repr(str(demo_sequence)))
    monkeypatch.chdir(tmp_path)
    namespace = {"my_camera_driver": _camera_driver(demo_sequence)}
    exec(compile(code, "README.md", "exec"), namespace)  # noqa: S102 - the README's own code

    from evtrack import Trajectory

    offline = Trajectory.load(tmp_path / "poses.csv")
    assert len(offline.t_us) >= 290  # one output per 1 ms step of the 0.3 s
    assert (offline.status == 1).any(), "the offline run never tracked"
    live = namespace["tracker"].trajectory()
    assert (live.status == 1).any(), "the live loop never tracked"
    assert np.isfinite(namespace["T"]).all() and namespace["T"].shape == (4, 4)
    assert namespace["V"].shape == (6,)
    assert (tmp_path / "pose.onnx").is_file()
