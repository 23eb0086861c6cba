"""``evtrack simulate`` and ``evtrack simulate-benchmark`` on tiny overrides."""

from __future__ import annotations

import pytest
import yaml

from evtrack import Sequence
from evtrack.cli import main


def test_simulate_command(tmp_path, capsys) -> None:
    out = tmp_path / "seq"
    args = ["simulate", "--object", "bottle", "--speed", "faster", "--duration", "0.04",
            "--seed", "2", "--width", "64", "--height", "48", "--out", str(out), "--quiet"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "events" in printed and "median" in printed
    seq = Sequence.load(out)
    assert seq.meta.event_camera.size == (64, 48) and seq.num_rgb == 2
    import os

    umask = os.umask(0o022)
    os.umask(umask)
    for folder in (out, out / "rgb", out / "depth"):  # readable by others as mkdir makes them
        assert folder.stat().st_mode & 0o777 == 0o777 & ~umask
    assert seq.meta.extra["config"]["trajectory"]["preset"] == "faster"
    assert seq.meta.extra["seed"] == 2
    # the folder exists now: refused without --overwrite, with a clean message
    assert main(args) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert main(args + ["--overwrite"]) == 0


def test_simulate_errors(tmp_path, capsys) -> None:
    base = ["simulate", "--duration", "0.02", "--width", "32", "--out", str(tmp_path / "x")]
    assert main(base + ["--object", "teapot"]) == 1
    assert "unknown object 'teapot'" in capsys.readouterr().err
    assert main(base + ["--object", str(tmp_path / "missing.glb")]) == 1
    assert "mesh file not found" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("events:\n  threshold_on: -1\n")
    assert main(base + ["--object", "can", "--config", str(bad)]) == 1
    assert f"{bad}: events.threshold_on: must be > 0, got -1.0" in capsys.readouterr().err
    zero = ["simulate", "--duration", "0.02", "--object", "can", "--out", str(tmp_path / "x")]
    assert main(zero + ["--width", "0", "--height", "120"]) == 1  # once: a 640x120 camera
    assert "--width must be positive, got 0" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_simulate_benchmark_command(tmp_path, ycb_dir, capsys) -> None:
    out = tmp_path / "bench"
    args = ["simulate-benchmark", "--out", str(out), "--duration", "0.03", "--width", "64",
            "--height", "48", "--objects", "005_tomato_soup_can", "--ycb-dir", str(ycb_dir),
            "--quiet"]
    assert main(args) == 0
    names = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert names == ["005_tomato_soup_can_faster", "005_tomato_soup_can_regular"]
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    rows = summary["sequences"]
    assert rows["005_tomato_soup_can_regular"]["seed"] != rows["005_tomato_soup_can_faster"]["seed"]
    assert set(summary["pixel_speed_px_s"]) == {"regular", "faster"}
    assert (out / "velocity_cdf.png").read_bytes()[:4] == b"\x89PNG"
    seq = Sequence.load(out / "005_tomato_soup_can_faster")
    assert seq.meta.object_name == "005_tomato_soup_can" and len(seq.events) > 0
    assert "005_tomato_soup_can_regular" in capsys.readouterr().out
    assert main(args) == 1  # exists
    assert main(["simulate-benchmark", "--out", str(out), "--objects", "teapot"]) == 1


def test_velocity_report_without_rendering(tmp_path, ycb_dir, capsys) -> None:
    out = tmp_path / "velocity"
    assert main(["simulate-benchmark", "--out", str(out), "--velocity-only", "--duration", "0.5",
                 "--ycb-dir", str(ycb_dir), "--objects", "010_potted_meat_can"]) == 0
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    speeds = summary["pixel_speed_px_s"]
    assert speeds["faster"]["p50"] > speeds["regular"]["p50"] > 0
    assert (out / "velocity_cdf.png").is_file()
    assert not any(p.is_dir() for p in out.iterdir())  # nothing rendered
    assert "010_potted_meat_can_faster" in capsys.readouterr().out


def test_preset_speeds_slow_a_preset_down(tmp_path, ycb_dir, capsys) -> None:
    """--preset-speeds replaces one preset's mean speeds: the same waypoints traversed at a
    third of the speed move the object's image slower; the other preset keeps its defaults;
    the speeds used are in the summary."""
    def report(out, *extra):
        assert main(["simulate-benchmark", "--out", str(out), "--velocity-only", "--duration",
                     "1.0", "--ycb-dir", str(ycb_dir), "--objects", "005_tomato_soup_can",
                     *extra]) == 0
        return yaml.safe_load((out / "summary.yaml").read_text())["sequences"]

    default = report(tmp_path / "default")
    slow = report(tmp_path / "slow", "--preset-speeds", "faster=0.27,0.83")
    fast_d, fast_s = default["005_tomato_soup_can_faster"], slow["005_tomato_soup_can_faster"]
    assert (fast_d["linear_speed_m_s"], fast_d["angular_speed_rad_s"]) == (0.8, 2.5)
    assert (fast_s["linear_speed_m_s"], fast_s["angular_speed_rad_s"]) == (0.27, 0.83)
    assert fast_s["pixel_speed_px_s"]["p50"] < 0.6 * fast_d["pixel_speed_px_s"]["p50"]
    assert slow["005_tomato_soup_can_regular"] == default["005_tomato_soup_can_regular"]
    capsys.readouterr()


@pytest.mark.parametrize("item, message", [
    ("faster", "expected PRESET=LINEAR,ANGULAR"),
    ("faster=0.5", "expected PRESET=LINEAR,ANGULAR"),
    ("slow=0.5,1", "unknown preset 'slow'"),
    ("faster=0.5,x", "must be numbers"),
    ("faster=0,1", "positive and finite"),
    ("faster=0.5,nan", "positive and finite"),
])
def test_preset_speeds_errors(tmp_path, capsys, item, message) -> None:
    out = tmp_path / "b"
    assert main(["simulate-benchmark", "--out", str(out), "--velocity-only",
                 "--preset-speeds", item]) == 1
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_preset_speeds_paper(tmp_path, ycb_dir, capsys) -> None:
    from evtrack.sim.benchmark_set import PAPER_MATCHED_SPEEDS

    out = tmp_path / "paper"
    assert main(["simulate-benchmark", "--out", str(out), "--velocity-only", "--duration",
                 "0.3", "--ycb-dir", str(ycb_dir), "--objects", "005_tomato_soup_can",
                 "--preset-speeds", "paper"]) == 0
    rows = yaml.safe_load((out / "summary.yaml").read_text())["sequences"]
    for preset, (linear, angular) in PAPER_MATCHED_SPEEDS.items():
        row = rows[f"005_tomato_soup_can_{preset}"]
        assert (row["linear_speed_m_s"], row["angular_speed_rad_s"]) == (linear, angular)
    assert main(["simulate-benchmark", "--out", str(tmp_path / "x"), "--velocity-only",
                 "--preset-speeds", "paper", "faster=0.5,1"]) == 1
    assert "give it alone" in capsys.readouterr().err


def test_preset_speeds_twice(tmp_path, capsys) -> None:
    assert main(["simulate-benchmark", "--out", str(tmp_path / "b"), "--velocity-only",
                 "--preset-speeds", "faster=0.5,1", "faster=0.6,1"]) == 1
    assert "'faster' given twice" in capsys.readouterr().err


def test_object_texture_follows_object_seed_not_trajectory_seed(tmp_path) -> None:
    import trimesh

    def texture(out, *extra):
        args = ["simulate", "--object", "box", "--duration", "0.02", "--width", "32",
                "--height", "24", "--out", str(out), "--quiet", *extra]
        assert main(args) == 0
        mesh = trimesh.load(out / "object.glb", force="mesh")
        return bytes(mesh.visual.material.baseColorTexture.tobytes())

    a = texture(tmp_path / "a", "--seed", "1")
    b = texture(tmp_path / "b", "--seed", "2")
    c = texture(tmp_path / "c", "--seed", "1", "--object-seed", "5")
    assert a == b and a != c
