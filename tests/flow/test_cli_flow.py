"""Smoke test of ``evtrack flow``: files written, bad options rejected cleanly."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.cli import main
from evtrack.flow.scenes import translating_texture


@pytest.fixture(scope="module")
def event_file(tmp_path_factory):
    from evtrack.io import write_events

    ev, _ = translating_texture((64, 48), velocity=(600.0, 250.0), duration_us=40_000, seed=5)
    path = tmp_path_factory.mktemp("flow_cli") / "events.h5"
    write_events(path, ev)
    return path


def test_flow_command_writes_flows_and_pictures(event_file, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["flow", str(event_file), "--out", str(out), "--window-ms", "5", "--roi", "32",
                 "--frame-ms", "10", "--video"])
    assert code == 0
    assert "RoI flows" in capsys.readouterr().out
    lines = (out / "flow.csv").read_text().splitlines()
    assert len(lines) > 10
    flow = np.array([[float(v) for v in line.split(",")[5:7]] for line in lines[1:]])
    assert np.median(np.linalg.norm(flow - [600.0, 250.0], axis=1)) < 0.1 * 650
    assert (out / "flow.png").stat().st_size > 1000
    assert (out / "flow.mp4").stat().st_size > 1000
    assert (out / "flow_config.yaml").is_file()
    assert not list(out.glob(".*tmp*"))


def test_flow_command_npz_with_event_flows(event_file, tmp_path):
    out = tmp_path / "out"
    assert main(["flow", str(event_file), "--out", str(out), "--format", "npz",
                 "--event-flow"]) == 0
    data = np.load(out / "flow.npz")
    assert data["event_flow"].shape[1] == 2 and data["flow"].shape[1] == 2


def test_flow_command_reports_bad_options(event_file, tmp_path, capsys):
    assert main(["flow", str(event_file), "--out", str(tmp_path), "--event-flow"]) == 1
    assert "--event-flow needs" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("radius: -1\n")
    assert main(["flow", str(event_file), "--out", str(tmp_path), "--config", str(bad)]) == 1
    assert "radius" in capsys.readouterr().err


def test_a_failed_flow_run_leaves_no_empty_output_folder(tmp_path, capsys):
    from evtrack.io import write_events

    ev, _ = translating_texture((64, 48), velocity=(300.0, 0.0), duration_us=20_000)
    good = tmp_path / "ev.h5"
    write_events(good, ev)
    truncated = tmp_path / "cut.h5"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    out = tmp_path / "flows"
    assert main(["flow", str(truncated), "--out", str(out)]) == 1
    assert "cut.h5" in capsys.readouterr().err
    assert not out.exists()
    assert main(["flow", str(good), "--out", str(out), "--read-ms", "nan"]) == 1
    assert "finite" in capsys.readouterr().err and not out.exists()


def test_flow_pictures_of_no_flows(tmp_path):
    """A recording without any RoI flow (sparse noise) still gives its pictures and video."""
    from evtrack.events import Events
    from evtrack.flow.visualize import flow_to_rgb
    from evtrack.io import write_events

    assert flow_to_rgb(np.zeros((0, 2), np.float32)).shape == (0, 3)
    rng = np.random.default_rng(0)
    n = 300
    ev = Events(rng.integers(0, 64, n), rng.integers(0, 48, n),
                np.sort(rng.integers(0, 40_000, n)), rng.choice([-1, 1], n), (64, 48))
    path = tmp_path / "noise.h5"
    write_events(path, ev)
    out = tmp_path / "out"
    assert main(["flow", str(path), "--out", str(out), "--frame-ms", "10", "--video"]) == 0
    assert (out / "flow.png").is_file() and (out / "flow.mp4").is_file()
    assert len((out / "flow.csv").read_text().splitlines()) == 1  # the header only


def test_flow_into_a_folder_of_an_earlier_run(event_file, tmp_path, capsys):
    """The outputs of an earlier run are not mixed with new ones: refused without
    --overwrite; with it they are replaced (an earlier format's file goes too) and the
    folder's other files stay."""
    out = tmp_path / "out"
    assert main(["flow", str(event_file), "--out", str(out), "--format", "npz"]) == 0
    (out / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(["flow", str(event_file), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "flow.npz" in err and "--overwrite" in err
    assert main(["flow", str(event_file), "--out", str(out), "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["flow.csv", "flow.png",
                                                      "flow_config.yaml", "notes.txt"]


def test_flow_overwrite_never_deletes_its_input(event_file, tmp_path, capsys):
    out = tmp_path / "f"
    out.mkdir()
    src = out / "flow.h5"  # an input named as one of the outputs
    src.write_bytes(event_file.read_bytes())
    assert main(["flow", str(src), "--out", str(out), "--overwrite"]) == 1
    assert "lies in" in capsys.readouterr().err
    assert src.read_bytes() == event_file.read_bytes()
