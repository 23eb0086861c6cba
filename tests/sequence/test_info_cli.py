"""``evtrack info`` on event files and sequence folders."""

from __future__ import annotations

import json

import numpy as np

from evtrack import Events
from evtrack.cli import main
from evtrack.io import write_events


def test_info_event_file(tmp_path, capsys):
    g = np.random.default_rng(0)
    n = 5000
    p = np.where(np.arange(n) < 1000, 1, -1)
    ev = Events(g.integers(3, 60, n), g.integers(5, 40, n), np.arange(n) * 100, p,
                sensor_size=(64, 48))
    write_events(tmp_path / "ev.h5", ev)
    assert main(["info", str(tmp_path / "ev.h5"), "--json", "--window-ms", "7"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["events"] == n
    assert out["sensor_size"] == [64, 48]
    assert abs(out["duration_s"] - (n - 1) * 1e-4) < 1e-12
    assert abs(out["on_fraction"] - 0.2) < 1e-12
    assert out["x_range"] == [int(ev.x.min()), int(ev.x.max())]
    assert main(["info", str(tmp_path / "ev.h5")]) == 0
    assert "Mev/s" in capsys.readouterr().out
    for bad in ("0", "-1", "nan", "inf"):  # once accepted, or a raw ValueError
        assert main(["info", str(tmp_path / "ev.h5"), "--window-ms", bad]) == 1
        assert "--window-ms must be a positive number" in capsys.readouterr().err


def test_info_missing_file(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nope.h5")]) == 1
    assert "nope.h5" in capsys.readouterr().err


def test_info_sequence(tmp_path, capsys, sequence_factory):
    sequence_factory().save(tmp_path / "seq")
    assert main(["info", str(tmp_path / "seq")]) == 0
    out = capsys.readouterr().out
    assert "rgb frames" in out and "2,000" in out and "poses" in out


def test_info_pose_network_files(tmp_path, capsys):
    """.pt weights and .onnx exports: their record, not an event-file error (a .pt is a zip,
    which the event readers took for an .npz and answered with a list of every tensor)."""
    import pytest
    import torch

    from evtrack.models import Cuboid, WeightsRecord, create, save_weights

    torch.manual_seed(0)
    record = WeightsRecord(arch="dope_lite_tiny", object_name="box",
                           cuboid=Cuboid((0.1, 0.2, 0.05), (0.0, 0.0, 0.01)), input_size=(72, 96),
                           decode={"crop_refine": 0.0})
    pt = save_weights(tmp_path / "box.pt", create("dope_lite_tiny"), record)
    assert main(["info", str(pt), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["object"] == "box" and out["arch"] == "dope_lite_tiny"
    assert out["input_size"].startswith("96x72") and out["decode"] == {"crop_refine": 0.0}
    assert out["cuboid"] == {"dimensions_m": [0.1, 0.2, 0.05], "center_m": [0.0, 0.0, 0.01]}
    assert "torch" in out["kind"]
    pytest.importorskip("onnxruntime")
    from evtrack.models import load_model
    from evtrack.models.onnx_export import export_onnx

    onnx_path = export_onnx(load_model(pt)[0], tmp_path / "box.onnx", fp16=True)
    assert main(["info", str(onnx_path)]) == 0
    text = capsys.readouterr().out
    assert "ONNX export (FP16, opset 18)" in text and "dope_lite_tiny" in text
    (tmp_path / "junk.pt").write_bytes(b"not a weights file")
    assert main(["info", str(tmp_path / "junk.pt")]) == 1
    err = capsys.readouterr().err
    assert "junk.pt" in err and len(err.splitlines()) == 1
