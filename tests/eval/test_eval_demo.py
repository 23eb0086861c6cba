"""``evtrack demo`` end to end on a tiny size with the oracle, and its errors."""

from __future__ import annotations

import csv

import pytest
from eval_helpers import save_tiny_weights

import evtrack.models.weights as weights_module
from evtrack import Sequence
from evtrack.cli import main
from evtrack.demo import DemoOptions, demo_tracker_config, demo_weights
from evtrack.errors import ConfigError
from evtrack.tracking.config import TrackerConfig

TINY = ["--size", "64x48", "--duration", "0.6", "--jobs", "1", "--quiet"]


def test_demo_with_the_oracle(tmp_path, capsys):
    import imageio.v3 as iio

    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--oracle", *TINY]) == 0
    printed = capsys.readouterr().out
    for text in ("velocity (events only)", "pose (5 Hz poses only)", "full (events + poses)",
                 "ORACLE", "position (cm)", str(out / "videos" / "coded_box_faster.mp4")):
        assert text in printed
    seq = Sequence.load(out / "coded_box_faster")
    assert seq.meta.object_name == "coded_box" and seq.meta.event_camera.size == (64, 48)
    assert seq.meta.extra["config"]["trajectory"]["preset"] == "faster"
    assert seq.meta.rates["render_hz"] == 4000.0  # event timing within 0.25 ms
    assert seq.meta.extra["object"]["source"] == "procedural:coded_box:seed=0"
    assert iio.imread(out / "videos" / "coded_box_faster.mp4").shape[0] == seq.num_rgb
    rows = [r for r in csv.DictReader((out / "results.csv").open()) if r["table"] == "sequence"]
    assert [r["run"] for r in rows] == ["velocity", "pose", "full"]
    for r in rows:  # the table printed holds the CSV's numbers
        assert f"{float(r['position_rmse_cm']):.2f} ± {float(r['position_std_cm']):.2f}" in printed
    for name in ("coded_box_faster_tracking.png", "error_vs_pixel_velocity.png",
                 "pixel_velocity_cdf.png"):
        assert (out / "plots" / name).stat().st_size > 5000
    # a second run refuses to mix its outputs with the first's, unless told to replace them
    assert main(["demo", "--out", str(out), "--oracle", *TINY]) == 1
    assert "--overwrite" in capsys.readouterr().err


def test_demo_without_weights_says_what_to_do(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(weights_module, "zoo_dir", lambda: tmp_path / "empty_zoo")
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), *TINY]) == 1
    err = capsys.readouterr().err
    assert "no shipped pose-network weights for the demo object 'coded_box'" in err
    assert "evtrack train --config configs/pose_demo_coded_box.yaml" in err and "--oracle" in err
    assert not out.exists()  # stopped before simulating


def test_demo_weights_lookup(tmp_path, monkeypatch):
    zoo = tmp_path / "zoo"
    save_tiny_weights(zoo / "can_dope_lite_tiny.pt", object_name="can")
    box = save_tiny_weights(zoo / "coded_box_dope_lite_tiny.pt", object_name="coded_box")
    monkeypatch.setattr(weights_module, "zoo_dir", lambda: zoo)
    assert demo_weights() == box
    assert demo_weights(box) == box
    with pytest.raises(ConfigError, match="trained on 'can'"):
        demo_weights(zoo / "can_dope_lite_tiny.pt")
    # an exported model is checked by its embedded record (make_pose_source runs an .onnx on
    # onnxruntime: tests/eval/test_eval_cli.py)
    pytest.importorskip("onnxruntime")
    from evtrack.models import load_model
    from evtrack.models.onnx_export import export_onnx

    onnx_box = export_onnx(load_model(box)[0], tmp_path / "box.onnx")
    assert demo_weights(onnx_box) == onnx_box
    with pytest.raises(ConfigError, match="trained on 'can'"):
        demo_weights(export_onnx(load_model(zoo / "can_dope_lite_tiny.pt")[0],
                                 tmp_path / "can.onnx"))


def test_demo_options_are_checked(tmp_path, capsys):
    with pytest.raises(ConfigError, match="--duration"):
        DemoOptions(duration=0.2)
    with pytest.raises(ConfigError, match="--size"):
        DemoOptions(size=(16, 12))
    assert main(["demo", "--out", str(tmp_path / "x"), "--weights", str(tmp_path / "no.pt")]) == 1
    assert "file not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["demo", "--size", "big"])
    assert demo_tracker_config(320).flow.roi_size == 16
    assert demo_tracker_config(64).flow.roi_size == 8
    # the mask margin scales with the width from the tracker's default (stated at 640 px)
    assert demo_tracker_config(320).mask_margin_px == TrackerConfig().mask_margin_px / 2
    assert not demo_tracker_config(320).depth_fusion.range
    assert demo_tracker_config(320, depth_range=True).depth_fusion.range
    assert not demo_tracker_config(320).depth_fusion.icp
    assert demo_tracker_config(320, depth_icp=True).depth_fusion.icp


def test_demo_depth_range_reaches_the_tracker(tmp_path, monkeypatch):
    """``evtrack demo --depth-range`` / ``--depth-icp`` hand the options to the tracker
    config of every run."""
    from evtrack import demo as demo_module

    seen = {}

    def fake_benchmark(sequences, runs, config, *args, **kwargs):
        seen["depth_range"] = config.depth_fusion.range
        seen["depth_icp"] = config.depth_fusion.icp
        raise RuntimeError("stop after the config")

    monkeypatch.setattr(demo_module, "_simulate", lambda opts, folder: None)
    monkeypatch.setattr(demo_module, "find_sequences", lambda folder: [])
    monkeypatch.setattr(demo_module, "run_benchmark", fake_benchmark)
    for flag, ranged, aligned in (([], False, False), (["--depth-range"], True, False),
                                  (["--depth-icp"], False, True)):
        with pytest.raises(RuntimeError, match="stop after the config"):
            main(["demo", "--out", str(tmp_path / "_".join(flag or ["plain"])), "--oracle",
                  *flag])
        assert seen.pop("depth_range") is ranged and seen.pop("depth_icp") is aligned
