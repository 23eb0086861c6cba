"""``evtrack import bop``: BOP scenes as sequence folders, tracked into BOP results."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from bop_scene import K_BOP, SIZE, pose, write_models, write_scene

from evtrack import Sequence
from evtrack.cli import main
from evtrack.datasets.bop import read_scene_gt
from evtrack.datasets.bop_import import import_bop_scene
from evtrack.datasets.bop_results import read_bop_results
from evtrack.geometry import integrate_twist
from evtrack.tracking.trajectory import Trajectory

T0 = pose([0.3, -0.2, 0.1], [0.05, -0.02, 0.6])
T1 = pose([0.35, -0.1, 0.15], [0.06, -0.02, 0.62])
T4 = pose([0.5, 0.1, 0.3], [0.08, -0.01, 0.65])


@pytest.fixture
def bop(tmp_path: Path) -> tuple[Path, Path]:
    """A scene ``000012`` with images 0, 1, 2, 4 (object 1 in 0, 1, 4; object 2 in 1) and its
    models folder."""
    gt = {0: [(1, T0)], 1: [(2, T4), (1, T1)], 2: [], 4: [(1, T4)]}
    depth = np.full((SIZE[1], SIZE[0]), 0.6789, np.float32)
    depth[3:6, 7:9] = 0.0
    scene = write_scene(tmp_path / "test" / "000012", gt, depths_m={1: depth})
    models = write_models(tmp_path / "models", obj_id=1)
    write_models(models, obj_id=2, size_mm=(30.0, 30.0, 30.0))
    return scene, models


def test_import_command(bop, tmp_path: Path, capsys) -> None:
    scene, models = bop
    out = tmp_path / "seq"
    args = ["import", "bop", str(scene), "--models", str(models), "--object", "1", "--out",
            str(out), "--fps", "10", "--quiet"]
    assert main(args) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    seq = Sequence.load(out)
    assert seq.rgb_times_us.tolist() == [0, 100_000, 200_000, 400_000]  # image id / fps
    assert seq.depth_times_us.tolist() == seq.rgb_times_us.tolist()
    from evtrack.datasets.bop import BopScene

    bs = BopScene(scene)
    for i, im_id in enumerate([0, 1, 2, 4]):
        np.testing.assert_array_equal(seq.rgb(i), bs.rgb(im_id))
    depth = seq.depth(1)
    assert depth[0, 0] == pytest.approx(0.679, abs=1e-6)  # stored to the millimetre
    assert np.isnan(depth[4, 8]) and np.isfinite(depth[0, 8])
    cam = seq.meta.rgb_camera
    assert cam.size == SIZE
    np.testing.assert_allclose(cam.K().numpy(), K_BOP)
    assert seq.meta.event_camera.size == SIZE and len(seq.events) == 0
    np.testing.assert_array_equal(seq.meta.T_event_rgb.numpy(), np.eye(4))
    assert seq.meta.extra["bop"] == {"scene_id": 12, "obj_id": 1, "im_ids": [0, 1, 4],
                                     "im_times_us": [0, 100_000, 400_000], "gt_frame": "rgb"}
    assert seq.meta.rates == {"rgb_hz": 10.0, "depth_hz": 10.0}
    gt = seq.ground_truth
    assert gt.pose_t_us.tolist() == [0, 100_000, 400_000]
    for T, t_us in zip((T0, T1, T4), (0, 100_000, 400_000), strict=True):
        np.testing.assert_allclose(gt.pose_at(t_us).numpy(), T, atol=1e-9)
    # twists move each pose to the next one over the time between them
    for k, (Ta, Tb, dt) in enumerate(((T0, T1, 0.1), (T1, T4, 0.3))):
        moved = integrate_twist(torch.from_numpy(Ta), gt.twists[k], dt).numpy()
        np.testing.assert_allclose(moved, Tb, atol=1e-9)
    from evtrack.sim.objects import load_mesh

    mesh = load_mesh(seq.mesh_file, recenter=False)  # metres, the BOP model's frame
    np.testing.assert_allclose(mesh.vertices.min(0), [-0.015, -0.033, -0.008], atol=1e-6)
    np.testing.assert_allclose(mesh.vertices.max(0), [0.025, 0.027, 0.012], atol=1e-6)
    assert main(args) == 1  # exists
    assert "--overwrite" in capsys.readouterr().err


def test_import_function_names_and_offsets(bop, tmp_path: Path) -> None:
    scene, models = bop
    out = import_bop_scene(scene, models, 2, tmp_path / "o2", fps=20.0, frame_offset_us=7,
                           scene_id=99, name="mine", progress=False)
    seq = Sequence.load(out)
    assert seq.meta.name == "mine" and seq.meta.object_name == "obj_000002"
    assert seq.rgb_times_us.tolist() == [7, 50_007, 100_007, 200_007]
    assert seq.meta.extra["bop"]["scene_id"] == 99
    assert seq.meta.extra["bop"]["im_ids"] == [1]
    assert seq.ground_truth.pose_t_us.tolist() == [50_007]


def _stderr_of(args: list[str], capsys) -> str:
    assert main(args) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1  # one line
    return err


def test_import_errors(bop, tmp_path: Path, capsys) -> None:
    scene, models = bop
    out = tmp_path / "seq"
    base = ["import", "bop", str(scene), "--models", str(models), "--out", str(out), "--quiet"]
    err = _stderr_of(base + ["--object", "3"], capsys)
    assert "object 3 is in no image; the scene holds obj_id [1, 2]" in err
    assert "scene_gt.json" in err
    (models / "obj_000002.ply").rename(models / "obj_000009.ply")
    err = _stderr_of(base + ["--object", "2"], capsys)
    assert "no model of object 2 (obj_000002.ply); the folder holds object ids [1, 9]" in err
    from evtrack import Events
    from evtrack.io import write_events

    write_events(tmp_path / "ev.h5", Events([1], [2], [3], [1], sensor_size=(64, 48)))
    err = _stderr_of(base + ["--object", "1", "--events", str(tmp_path / "ev.h5")], capsys)
    assert "the events' sensor is 64x48 but the BOP images are 160x120" in err
    named = scene.parent / "scene_a"
    scene.rename(named)
    err = _stderr_of(["import", "bop", str(named), "--models", str(models), "--object", "1",
                      "--out", str(out)], capsys)
    assert "not a BOP scene id; pass scene_id (--scene-id)" in err
    (named / "scene_camera.json").unlink()
    err = _stderr_of(["import", "bop", str(named), "--models", str(models), "--object", "1",
                      "--out", str(out), "--scene-id", "3"], capsys)
    assert f"{named / 'scene_camera.json'}: file not found" in err
    assert not out.exists()


def test_nothing_half_written(bop, tmp_path: Path, capsys) -> None:
    scene, models = bop
    (scene / "depth" / "000004.png").unlink()  # the last frame's depth
    out = tmp_path / "seqs" / "s"
    err = _stderr_of(["import", "bop", str(scene), "--models", str(models), "--object", "1",
                      "--out", str(out), "--quiet"], capsys)
    assert "000004.png: depth image of image 4 not found" in err
    assert list((tmp_path / "seqs").iterdir()) == []  # no sequence, no temporary folder


def test_track_needs_a_bop_record(tmp_path: Path, capsys) -> None:
    from evtrack.sim.engine import simulate
    from evtrack.sim.objects import procedural_object

    simulate(procedural_object("box", 0), _sim_config(0.02), tmp_path / "sim")
    err = _stderr_of(["track", str(tmp_path / "sim"), "--out", str(tmp_path / "t.csv"),
                      "--oracle", "--bop-results", str(tmp_path / "r.csv"), "--quiet"], capsys)
    assert "meta.yaml extra.bop is missing" in err
    assert not (tmp_path / "t.csv").exists()


# ---------------------------------------------------------------------------- end to end
def _sim_config(duration: float):
    from evtrack.sim.config import EventConfig, GroundTruthConfig, SimConfig, TrajectoryConfig

    cfg = SimConfig(duration=duration, seed=3, trajectory=TrajectoryConfig(preset="faster"),
                    events=EventConfig(threshold_on=0.5, threshold_off=0.5),
                    ground_truth=GroundTruthConfig(event_flow=False))
    return dataclasses.replace(cfg, camera=cfg.camera.resized(128, 96))


FPS = 60.0
OFFSET_US = 8333  # the simulator's first frame: the mean time of its first exposure


def _bop_from_simulation(seq: Sequence, root: Path) -> tuple[Path, Path, Path]:
    """The simulated sequence as a BOP scene (images at OFFSET_US + im_id / FPS, ground truth
    at those times, depth in units of 0.1 mm), its model in mm and its events file."""
    import trimesh

    from evtrack.io import write_events
    from evtrack.sim.objects import load_mesh

    mesh = load_mesh(seq.mesh_file, recenter=False)
    models = root / "models"
    models.mkdir(parents=True)
    trimesh.Trimesh(mesh.vertices.astype(np.float64) * 1000.0, mesh.faces,
                    process=False).export(models / "obj_000001.ply")
    (models / "models_info.json").write_text(json.dumps(
        {"1": {"diameter": float(np.linalg.norm(mesh.extents)) * 1000.0}}))
    ids = list(range(seq.num_rgb))
    times = OFFSET_US + np.round(np.asarray(ids) * 1e6 / FPS).astype(np.int64)
    poses = seq.ground_truth.pose_at(torch.from_numpy(times)).numpy()
    gt = {k: [(1, poses[k])] for k in ids}
    scene = write_scene(root / "test" / "000003", gt, {k: seq.rgb(k) for k in ids},
                        {k: seq.depth(k) for k in ids}, K=seq.meta.rgb_camera.K().numpy())
    write_events(root / "events.h5", seq.events)
    return scene, models, root / "events.h5"


def test_import_track_and_write_bop_results(tmp_path: Path, capsys) -> None:
    from evtrack.sim.engine import simulate
    from evtrack.sim.objects import procedural_object

    simulate(procedural_object("box", 0), _sim_config(0.3), tmp_path / "sim")
    sim = Sequence.load(tmp_path / "sim")
    scene, models, events = _bop_from_simulation(sim, tmp_path / "bop")
    out = tmp_path / "imported"
    assert main(["import", "bop", str(scene), "--models", str(models), "--object", "1",
                 "--events", str(events), "--fps", str(FPS), "--frame-offset-us",
                 str(OFFSET_US), "--out", str(out), "--quiet"]) == 0
    seq = Sequence.load(out)
    assert len(seq.events) == len(sim.events) > 10_000
    assert np.abs(seq.rgb_times_us.numpy() - sim.rgb_times_us.numpy()).max() <= 1000
    both = np.isfinite(seq.depth(5)) & np.isfinite(sim.depth(5))  # 0.1 mm units, then mm
    assert both.mean() > 0.9
    assert np.abs(seq.depth(5)[both] - sim.depth(5)[both]).max() <= 0.00051
    config = tmp_path / "tracker.yaml"
    config.write_text("flow: {roi_size: 16}\nmask_margin_px: 8.0\npose_rate_hz: 10.0\n"
                      "pose_latency_ms: 100.0\n")
    results = tmp_path / "method_bop-test.csv"
    assert main(["track", str(out), "--out", str(tmp_path / "traj.csv"), "--oracle",
                 "--config", str(config), "--bop-results", str(results), "--quiet"]) == 0
    assert f"{results}:" in capsys.readouterr().out
    rows = read_bop_results(results)
    truth = read_scene_gt(scene / "scene_gt.json")
    assert len(rows) >= 0.5 * len(truth)  # the first pose comes after 100 ms of latency
    assert {(r.scene_id, r.obj_id) for r in rows} == {(3, 1)}
    # each row is the trajectory's pose at its image's time (samples are 1 ms apart)
    traj = Trajectory.load(tmp_path / "traj.csv")
    for r in rows:
        t_us = OFFSET_US + round(r.im_id * 1e6 / FPS)
        k = int(np.searchsorted(traj.t_us.numpy(), t_us, side="right")) - 1
        assert bool(traj.tracked[k]) and t_us - int(traj.t_us[k]) < 1000
        np.testing.assert_allclose(r.T_m2c[:3, 3], traj.poses[k, :3, 3].numpy(), atol=2e-3)
    # and near the truth: this short clip tracks to about 3 cm (a unit or frame slip: 10x more)
    errors = [np.linalg.norm(r.T_m2c[:3, 3] - truth[r.im_id][0].T_m2c[:3, 3]) for r in rows]
    assert np.median(errors) < 0.06, errors
