"""Several objects end to end: ``evtrack simulate --object A --object B``, the multi-object
sets, and ``evtrack evaluate`` per object (together and alone)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from eval_helpers import TINY_TRACKER_YAML

from evtrack import Sequence
from evtrack.cli import main
from evtrack.eval.metrics import tracking_errors
from evtrack.eval.multi_object import (
    HIDDEN_FROM,
    VISIBLE_BELOW,
    occluded_share,
    occlusion_timeline,
)
from evtrack.sim.benchmark_set import BENCHMARK_SEEDS, MAX_SEEDS, split_seed
from evtrack.sim.multi_object_set import MULTI_OBJECT_SETS, multi_object_entries
from evtrack.tracking.trajectory import Trajectory


@pytest.fixture(scope="module")
def two_object_bench(tmp_path_factory):
    bench = tmp_path_factory.mktemp("multi") / "bench"
    for layout in ("apart", "crossing"):
        args = ["simulate", "--object", "box", "--object", "can", "--layout", layout,
                "--duration", "0.4", "--seed", "3", "--width", "128", "--height", "96",
                "--out", str(bench / layout), "--quiet"]
        assert main(args) == 0
    cfg = bench.parent / "tracker.yaml"
    cfg.write_text(TINY_TRACKER_YAML)
    return bench, cfg


@pytest.fixture(scope="module")
def evaluated(two_object_bench):
    bench, cfg = two_object_bench
    out = bench.parent / "results"
    assert main(["evaluate", "--benchmark", str(bench), "--oracle", "--config", str(cfg),
                 "--out", str(out), "--quiet"]) == 0
    return out


def test_simulate_writes_several_objects(two_object_bench) -> None:
    bench, _ = two_object_bench
    seq = Sequence.load(bench / "apart")
    assert [o.name for o in seq.objects] == ["box", "can"]
    assert seq.meta.extra["config"]["trajectory"]["layout"] == "apart"
    assert set(np.unique(seq.ground_truth.event_object.numpy())) >= {0, 1}


def test_simulate_refuses_a_repeated_object_and_a_lone_layout(tmp_path, capsys) -> None:
    base = ["simulate", "--duration", "0.02", "--width", "32", "--out", str(tmp_path / "x")]
    assert main(base + ["--object", "box", "--object", "box"]) == 1
    assert "each object must be another one" in capsys.readouterr().err
    assert main(base + ["--object", "box", "--layout", "apart"]) == 1
    assert "give --object more than once" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_evaluate_reports_each_object_together_and_alone(evaluated, two_object_bench) -> None:
    bench, _ = two_object_bench
    out = evaluated
    rows = list(csv.DictReader((out / "multi_object.csv").open()))
    assert {(r["sequence"], r["object"]) for r in rows} == {
        (s, o) for s in ("apart", "crossing") for o in ("box", "can")}
    for r in rows:
        seq = Sequence.load(bench / r["sequence"])
        k = [o.name for o in seq.objects].index(r["object"])
        for mode in ("together", "alone"):
            traj = Trajectory.load(out / "trajectories" / r["sequence"] /
                                   f"full-{r['object']}-{mode}.h5")
            ref = tracking_errors(traj, seq.object_ground_truth(k))
            assert float(r[f"{mode}_cm"]) == pytest.approx(ref.position_rmse_cm, abs=1e-3)
            assert float(r[f"{mode}_deg"]) == pytest.approx(ref.rotation_rmse_deg, abs=1e-3)
    # visible / hidden: the together run's errors over the samples under 5 % / from 25 % hidden
    for r in rows:
        seq = Sequence.load(bench / r["sequence"])
        k = [o.name for o in seq.objects].index(r["object"])
        times, shares = occlusion_timeline(seq)
        traj = Trajectory.load(out / "trajectories" / r["sequence"] /
                               f"full-{r['object']}-together.h5")
        t = traj.t_us.numpy()
        share = shares[k][np.abs(t[:, None] - times[None, :]).argmin(axis=1)]
        for key, part in (("visible", share < VISIBLE_BELOW), ("hidden", share >= HIDDEN_FROM)):
            if not (part & traj.tracked.numpy()).any():
                assert r[f"{key}_cm"] == ""
                continue
            ref = tracking_errors(traj[torch.from_numpy(part)], seq.object_ground_truth(k))
            assert float(r[f"{key}_cm"]) == pytest.approx(ref.position_rmse_cm, abs=1e-3)
            assert float(r[f"{key}_deg"]) == pytest.approx(ref.rotation_rmse_deg, abs=1e-3)
    assert any(r["hidden_cm"] for r in rows)  # the crossing hides an object at times
    text = (out / "multi_object.md").read_text()
    assert "ORACLE" in text and "Averages per set and layout" in text
    assert "| 2 objects | apart | full | 2 |" in text
    manifest = yaml.safe_load((out / "multi_object.yaml").read_text())
    assert len(manifest["timings"]) == 2 and len(manifest["objects"]) == 4


def test_evaluate_refuses_a_mixed_benchmark_and_single_object_options(
        two_object_bench, tiny_benchmark, tmp_path, capsys) -> None:
    import shutil

    bench, cfg = two_object_bench
    mixed = tmp_path / "mixed"
    shutil.copytree(bench / "apart", mixed / "apart")
    shutil.copytree(tiny_benchmark / "box_regular", mixed / "box_regular")
    assert main(["evaluate", "--benchmark", str(mixed), "--oracle", "--quiet"]) == 1
    assert "mixes one-object sequences" in capsys.readouterr().err
    assert main(["evaluate", "--benchmark", str(bench), "--oracle", "--ablation",
                 "--out", str(tmp_path / "r"), "--quiet"]) == 1
    assert "--ablation is for one-object sequences" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_occlusion_is_zero_apart_and_on_the_far_object_when_crossing(two_object_bench) -> None:
    bench, _ = two_object_bench
    assert occluded_share(Sequence.load(bench / "apart")) == [0.0, 0.0]
    near, far = occluded_share(Sequence.load(bench / "crossing"))
    assert near == 0.0 and far >= 0.0  # object 0 has the nearest depth band


def test_multi_object_sets_have_their_own_seeds() -> None:
    entries = multi_object_entries(("two", "four"), ("regular", "faster"))
    seeds = [e.seed for e in entries]
    assert len(set(seeds)) == len(seeds) == 2 * 2 * (len(MULTI_OBJECT_SETS["two"]) + 1)
    single = set(BENCHMARK_SEEDS.values()) | {
        split_seed(s, i, j, k) for s in ("tuning", "test") for i in range(4) for j in range(2)
        for k in range(MAX_SEEDS)}
    assert not set(seeds) & single
    assert len({e.folder_name for e in entries}) == len(entries)
    assert entries[0].folder_name == "two/tomato_soup_can+cracker_box_apart_regular"


@pytest.mark.parametrize("options", [["--oracle"], ["--mesh-only", "--start-from-ground-truth"]])
def test_track_writes_one_trajectory_per_object(two_object_bench, tmp_path, capsys,
                                                options) -> None:
    bench, cfg = two_object_bench
    out = tmp_path / "track.h5"
    assert main(["track", str(bench / "apart"), "--config", str(cfg), "--out", str(out),
                 "--quiet", *options]) == 0
    printed = capsys.readouterr().out
    seq = Sequence.load(bench / "apart")
    for k, name in enumerate(("box", "can")):
        traj = Trajectory.load(tmp_path / f"track_{name}.h5")
        assert bool(traj.tracked.any()) and f"track_{name}.h5" in printed
        err = tracking_errors(traj, seq.object_ground_truth(k))
        assert err.position_rmse_cm < 5.0
    assert "2 objects" in printed and not out.exists()


def test_track_finds_each_objects_start(tmp_path, capsys) -> None:
    """``--mesh-only --start-find``: each object's start found on the first RGB-D frame
    without a box (at 320x240: at 128x96 the can covers too few pixels for its texture)."""
    seq_dir = tmp_path / "apart"
    assert main(["simulate", "--object", "box", "--object", "can", "--layout", "apart",
                 "--duration", "0.1", "--seed", "3", "--width", "320", "--height", "240",
                 "--out", str(seq_dir), "--quiet"]) == 0
    cfg = tmp_path / "tracker.yaml"
    cfg.write_text(TINY_TRACKER_YAML)
    out = tmp_path / "track.h5"
    assert main(["track", str(seq_dir), "--config", str(cfg), "--out", str(out), "--quiet",
                 "--mesh-only", "--start-find"]) == 0
    printed = capsys.readouterr().out
    assert "box: start pose registered" in printed and "can: start pose registered" in printed
    seq = Sequence.load(seq_dir)
    for k, name in enumerate(("box", "can")):
        traj = Trajectory.load(tmp_path / f"track_{name}.h5")
        err = tracking_errors(traj, seq.object_ground_truth(k), t_end_us=int(traj.t_us[0]) + 1)
        assert err.samples == 1 and err.position_rmse_cm < 2.0 and err.rotation_rmse_deg < 3.0
    assert main(["track", str(seq_dir), "--out", str(out), "--mesh-only", "--start-find",
                 "--start-from-ground-truth"]) == 1
    assert "give one start" in capsys.readouterr().err

    from evtrack.tracking.config import TrackerConfig
    from evtrack.tracking.multi import MultiTracker

    multi = MultiTracker.for_sequence(seq, TrackerConfig.from_dict({"pose_source": "model"}))
    t0 = int(seq.rgb_times_us[0])
    found = multi.start_from_frame(t0, seq.rgb(0), seq.depth(0))
    assert set(found) == {"box", "can"}
    for k, name in enumerate(("box", "can")):
        tracker = multi.trackers[name]
        assert tracker.initialized and tracker.now_us == t0
        truth = seq.object_ground_truth(k).pose_at(t0).numpy()
        assert np.linalg.norm(tracker.pose()[:3, 3] - truth[:3, 3]) < 0.02  # the can: 1.1 cm
    with pytest.raises(ValueError, match="object 'box': .*no valid pixel"):
        multi.start_from_frame(t0, seq.rgb(0), np.zeros_like(seq.depth(0)))


def test_track_refuses_one_object_options_on_several(two_object_bench, tmp_path,
                                                     capsys) -> None:
    bench, _ = two_object_bench
    out = tmp_path / "t.csv"
    assert main(["track", str(bench / "apart"), "--weights", "w.pt", "--out", str(out)]) == 1
    assert "--weights is for one object" in capsys.readouterr().err
    assert main(["track", str(bench / "apart"), "--mesh-only", "--start-pose",
                 "--out", str(out)]) == 1
    assert "--start-pose is for one object" in capsys.readouterr().err
    assert main(["track", str(bench / "apart"), "--mesh-only", "--out", str(out)]) == 1
    assert "needs --start-from-ground-truth" in capsys.readouterr().err


def test_evaluate_names_an_object_without_ground_truth(two_object_bench, tmp_path,
                                                      capsys) -> None:
    import shutil

    bench, _ = two_object_bench
    copy = tmp_path / "bench" / "apart"
    shutil.copytree(bench / "apart", copy)
    (copy / "objects" / "1" / "groundtruth.h5").unlink()
    assert main(["evaluate", "--benchmark", str(tmp_path / "bench"), "--oracle",
                 "--out", str(tmp_path / "r"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "['can'] have no ground truth" in err and "apart" in err
    assert not (tmp_path / "r").exists()


def test_object_views_of_a_sequence_loaded_by_a_relative_path(two_object_bench,
                                                             monkeypatch) -> None:
    """Each object's view names its own mesh file (relative to the same folder), also when the
    sequence was loaded by a relative path (``evaluate --benchmark multi --jobs 2``)."""
    bench, _ = two_object_bench
    monkeypatch.chdir(bench.parent)
    seq = Sequence.load(Path(bench.name) / "apart")
    for k in range(len(seq.objects)):
        view = seq.object_view(k)
        assert view.mesh_file == seq.object_mesh_file(k) and view.mesh_file.is_file()
        assert view.meta.object_name == seq.objects[k].name
