"""``evtrack evaluate`` end to end on a tiny simulated benchmark, and its input errors."""

from __future__ import annotations

import csv
import shutil

import numpy as np
import pytest
import yaml
from eval_helpers import TINY_TRACKER_YAML, reference_errors, save_tiny_weights

from evtrack import Sequence
from evtrack.cli import main
from evtrack.errors import ConfigError
from evtrack.eval.benchmark import run_benchmark, run_one, run_specs
from evtrack.eval.pose_setup import PoseSourceSpec, resolve_weights
from evtrack.eval.sequences import find_sequences
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.trajectory import Trajectory


def rows_of(path):
    return list(csv.DictReader(path.open()))


@pytest.fixture(scope="module")
def evaluated(tiny_benchmark, tiny_tracker_yaml, tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluate") / "results"
    code = main(["evaluate", "--benchmark", str(tiny_benchmark), "--oracle", "--config",
                 str(tiny_tracker_yaml), "--methods", "full", "pose", "--ablation", "--video",
                 "--out", str(out), "--quiet"])
    assert code == 0
    return out


def test_evaluate_writes_everything(evaluated, tiny_benchmark):
    import imageio.v3 as iio

    out = evaluated
    for name in ("results.md", "results.csv", "results.yaml"):
        assert (out / name).stat().st_size > 100
    runs = {"full", "pose", "full-no-normal-flow", "full-no-weighting", "full-velocity-bias",
            "full-depth-range", "full-depth-icp"}
    for seq in ("box_regular", "box_faster"):
        assert {p.stem for p in (out / "trajectories" / seq).glob("*.h5")} == runs
        assert (out / "plots" / f"{seq}_tracking.png").stat().st_size > 5000
        frames = iio.imread(out / "videos" / f"{seq}.mp4")
        assert frames.shape[0] == Sequence.load(tiny_benchmark / seq).num_rgb
    for name in ("error_vs_pixel_velocity.png", "pixel_velocity_cdf.png"):
        assert (out / "plots" / name).stat().st_size > 5000
    text = (out / "results.md").read_text()
    assert "ORACLE" in text and "Table III" in text
    manifest = yaml.safe_load((out / "results.yaml").read_text())
    assert len(manifest["results"]) == 14 and manifest["tracker_config"]["pose_rate_hz"] == 10.0
    assert not list(out.rglob(".*tmp*"))


def test_evaluate_numbers_match_an_independent_computation(evaluated, tiny_benchmark):
    rows = rows_of(evaluated / "results.csv")
    per_seq = {}
    for r in (r for r in rows if r["table"] == "sequence"):
        seq = Sequence.load(tiny_benchmark / r["sequence"])
        traj = Trajectory.load(evaluated / "trajectories" / r["sequence"] / f"{r['run']}.h5")
        use = traj.tracked.numpy()
        assert use.sum() > 50 and int(r["samples"]) == use.sum()
        assert int(r["total"]) == len(traj)
        est = traj.poses.numpy()[use]
        true = seq.ground_truth.pose_at(traj.t_us[use]).numpy()
        ref = reference_errors(est, true)
        for key, value in ref.items():
            assert float(r[key]) == pytest.approx(value, rel=1e-6, abs=1e-9), (r["run"], key)
        per_seq.setdefault(r["run"], []).append(ref)
        assert r["speed"] == r["sequence"].split("_")[1] and r["object"] == "box"
    for r in (r for r in rows if r["table"] == "average" and r["speed"] == "all"):
        refs = per_seq[r["run"]]
        assert float(r["position_rmse_cm"]) == pytest.approx(
            np.mean([x["position_rmse_cm"] for x in refs]), rel=1e-6)
        assert float(r["rotation_std_deg"]) == pytest.approx(
            np.mean([x["rotation_std_deg"] for x in refs]), rel=1e-6)


def test_evaluate_pose_scores_match_an_independent_computation(evaluated, tiny_benchmark):
    """ADD / ADD-S AUC and 5 cm / 5° per sequence from the one-pose functions, every
    ground-truth sample scored with the latest trajectory sample (untracked: a failure)."""
    from scipy.spatial.transform import Rotation

    from evtrack.eval.pose_metrics import add_distance, adds_distance, object_diameter
    from evtrack.sim.objects import load_mesh

    rows = rows_of(evaluated / "results.csv")
    manifest = yaml.safe_load((evaluated / "results.yaml").read_text())
    listed = {(r["sequence"], r["run"]): r["pose_scores"] for r in manifest["results"]}
    positive = 0
    for r in (r for r in rows if r["table"] == "sequence"):
        seq = Sequence.load(tiny_benchmark / r["sequence"])
        traj = Trajectory.load(evaluated / "trajectories" / r["sequence"] / f"{r['run']}.h5")
        points = load_mesh(seq.mesh_file, recenter=False).vertices.astype(np.float64)
        assert len(points) <= 1000  # all of them: no subsampling
        tau = 0.1 * object_diameter(points)
        gt = seq.ground_truth
        t_traj, status = traj.t_us.numpy(), traj.status.numpy()
        add, adds, ok = [], [], []
        for t, T_true in zip(gt.pose_t_us.numpy(), gt.poses.numpy(), strict=True):
            k = np.searchsorted(t_traj, t, side="right") - 1
            if k < 0 or status[k] != 1:
                add.append(np.inf), adds.append(np.inf), ok.append(False)
                continue
            T = traj.poses.numpy()[k]
            add.append(add_distance(T, T_true, points))
            adds.append(adds_distance(T, T_true, points))
            angle = np.rad2deg(Rotation.from_matrix(T_true[:3, :3].T @ T[:3, :3]).magnitude())
            ok.append(np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.05 and angle < 5.0)
        add_auc = 100 * np.mean(np.clip(1 - np.asarray(add) / tau, 0, 1))
        adds_auc = 100 * np.mean(np.clip(1 - np.asarray(adds) / tau, 0, 1))
        assert float(r["add_auc_pct"]) <= float(r["adds_auc_pct"]) + 1e-9 < 100
        positive += float(r["adds_auc_pct"]) > 0
        assert float(r["add_auc_pct"]) == pytest.approx(add_auc, rel=1e-6)
        assert float(r["adds_auc_pct"]) == pytest.approx(adds_auc, rel=1e-6)
        assert float(r["within_5cm_5deg_pct"]) == pytest.approx(100 * np.mean(ok), rel=1e-9)
        assert float(r["diameter_cm"]) == pytest.approx(1000 * tau)
        scores = listed[(r["sequence"], r["run"])]
        assert scores["samples"] == len(gt.pose_t_us) and scores["note"] == ""
        assert scores["add_auc"] == pytest.approx(add_auc, rel=1e-6)
    assert positive >= 4  # most runs score above 0: the comparison is not of zeros
    text = (evaluated / "results.md").read_text()
    assert "## Pose accuracy per sequence: ADD / ADD-S AUC" in text


def test_each_run_is_reproducible_on_its_own(evaluated, tiny_benchmark, tiny_tracker_yaml,
                                             tmp_path):
    """The pose run alone (same oracle seed) gives the trajectory it gave among the others."""
    seqs = find_sequences(tiny_benchmark / "box_faster")
    base = TrackerConfig.from_yaml(tiny_tracker_yaml)
    res = run_one(seqs[0], run_specs(["pose"])[0], base, PoseSourceSpec("oracle"), None, tmp_path)
    a = Trajectory.load(res.trajectory)
    b = Trajectory.load(evaluated / "trajectories" / "box_faster" / "pose.h5")
    assert np.array_equal(a.poses.numpy(), b.poses.numpy(), equal_nan=True)
    assert np.array_equal(a.status.numpy(), b.status.numpy())


def test_network_pose_source(tiny_benchmark, tiny_tracker_yaml, tmp_path):
    """Weights found recursively by object; the network runs in the tracker (no plots here)."""
    weights = save_tiny_weights(tmp_path / "w" / "sub" / "box_tiny.pt")
    save_tiny_weights(tmp_path / "w" / "can_tiny.pt", object_name="can")
    spec = PoseSourceSpec("network", weights_dir=tmp_path / "w")
    seqs = find_sequences(tiny_benchmark)
    found = resolve_weights(spec, [s.object_name for s in seqs])
    assert found == {"box": weights}
    base = TrackerConfig.from_yaml(tiny_tracker_yaml)
    (res,) = run_benchmark(seqs[:1], run_specs(["pose"]), base, spec, found, tmp_path / "o",
                           progress=False)
    assert res.stats["pose_calls"] > 0 and res.trajectory.is_file()
    assert "pose network" in spec.label and "ORACLE" not in spec.label


def test_missing_weights_is_a_clear_error(tiny_benchmark, tmp_path, capsys):
    save_tiny_weights(tmp_path / "w" / "can.pt", object_name="can")
    code = main(["evaluate", "--benchmark", str(tiny_benchmark), "--weights-dir",
                 str(tmp_path / "w"), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1
    assert "no pose-network weights for object 'box'" in err
    assert "evtrack train --config configs/pose_demo_box.yaml" in err and "--oracle" in err
    assert not (tmp_path / "o").exists()


def test_oracle_where_missing_gives_the_oracle_to_objects_without_weights(
        evaluated, tiny_benchmark, tiny_tracker_yaml, tmp_path, capsys):
    """No weights for 'box': its runs get the oracle, the same trajectory as with --oracle
    (same seed), and the caption, the console and the manifest say so."""
    save_tiny_weights(tmp_path / "w" / "can.pt", object_name="can")
    out = tmp_path / "o"
    code = main(["evaluate", "--benchmark", str(tiny_benchmark / "box_faster"), "--weights-dir",
                 str(tmp_path / "w"), "--oracle-where-missing", "--config",
                 str(tiny_tracker_yaml), "--methods", "pose", "--out", str(out), "--quiet"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "ORACLE" in printed and "for box (no weights)" in printed
    assert "for box (no weights)" in (out / "results.md").read_text()
    assert yaml.safe_load((out / "results.yaml").read_text())["weights"] == {"box": "oracle"}
    a = Trajectory.load(out / "trajectories" / "box_faster" / "pose.h5")
    b = Trajectory.load(evaluated / "trajectories" / "box_faster" / "pose.h5")
    assert np.array_equal(a.poses.numpy(), b.poses.numpy(), equal_nan=True)


def test_oracle_where_missing_keeps_the_network_where_there_are_weights(tiny_benchmark,
                                                                         tmp_path):
    from evtrack.eval.pose_setup import make_pose_source, pose_caption
    from evtrack.tracking.pose_sources import NetworkPoseSource, OraclePoseSource

    weights = save_tiny_weights(tmp_path / "w" / "box.pt")
    spec = PoseSourceSpec("network", weights_dir=tmp_path / "w", oracle_fallback=True)
    found = resolve_weights(spec, ["box", "can", "box"])
    assert found == {"box": weights}
    caption = pose_caption(spec, found, ["box", "can"])
    assert caption.startswith("pose network") and "ORACLE" in caption and "for can" in caption
    assert pose_caption(spec, found, ["box"]) == spec.label  # nothing missing: no oracle
    seq = Sequence.load(tiny_benchmark / "box_regular")
    assert isinstance(make_pose_source(spec, seq, weights), NetworkPoseSource)
    assert isinstance(make_pose_source(spec, seq, None), OraclePoseSource)
    # without the fallback a missing object stays an error
    with pytest.raises(ConfigError, match="no pose-network weights for object 'can'"):
        resolve_weights(PoseSourceSpec("network", weights_dir=tmp_path / "w"), ["box", "can"])


def test_bad_benchmark_folders(tmp_path, tiny_benchmark, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["evaluate", "--benchmark", str(empty), "--oracle"]) == 1
    assert "no sequence folders found" in capsys.readouterr().err
    assert main(["evaluate", "--benchmark", str(tmp_path / "nope"), "--oracle"]) == 1
    assert "benchmark folder not found" in capsys.readouterr().err
    # one sequence without ground truth among good ones: named, nothing run
    bench = tmp_path / "bench"
    shutil.copytree(tiny_benchmark / "box_regular", bench / "a" / "good")
    shutil.copytree(tiny_benchmark / "box_faster", bench / "b" / "no_gt")
    (bench / "b" / "no_gt" / "groundtruth.h5").unlink()
    assert main(["evaluate", "--benchmark", str(bench), "--oracle", "--out",
                 str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "no ground truth" in err and str(bench / "b" / "no_gt") in err
    assert str(bench / "a" / "good") not in err and not (tmp_path / "o").exists()
    # a broken meta.yaml is named too
    (bench / "a" / "good" / "meta.yaml").write_text("format_version: 1\n")
    assert main(["evaluate", "--benchmark", str(bench), "--oracle"]) == 1
    assert "meta.yaml" in capsys.readouterr().err


def test_bad_options(tiny_benchmark, capsys):
    bench = str(tiny_benchmark)
    assert main(["evaluate", "--benchmark", bench, "--oracle-noise", "0.01", "0.02"]) == 1
    assert "--oracle-noise needs --oracle" in capsys.readouterr().err
    assert main(["evaluate", "--benchmark", bench, "--oracle", "--oracle-noise", "-1", "0"]) == 1
    assert "must be finite and >= 0" in capsys.readouterr().err
    assert main(["evaluate", "--benchmark", bench, "--oracle", "--depth-refine"]) == 1
    assert "--depth-refine refines a pose network's poses" in capsys.readouterr().err
    assert main(["evaluate", "--benchmark", bench, "--oracle", "--oracle-where-missing"]) == 1
    assert "with --oracle every object gets the oracle already" in capsys.readouterr().err
    assert main(["evaluate", "--benchmark", bench, "--oracle", "--jobs", "0"]) == 1
    assert "--jobs must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["evaluate", "--benchmark", bench, "--methods", "teleport"])
    with pytest.raises(SystemExit):
        main(["evaluate", "--benchmark", bench, "--oracle", "--weights-dir", bench])


def test_help_explains(capsys):
    with pytest.raises(SystemExit):
        main(["evaluate", "--help"])
    text = capsys.readouterr().out
    for word in ("--benchmark", "--ablation", "--oracle", "--weights-dir", "RMSE", "ORACLE",
                 "results.csv", "--jobs", "ADD-S AUC", "5 cm"):
        assert word in text


def test_pose_warnings_name_sequences_without_any_pose(tmp_path):
    from evtrack.eval.benchmark import RunResult, pose_warnings
    from evtrack.eval.metrics import TrackingErrors

    nan = float("nan")
    err = TrackingErrors(nan, nan, nan, nan, 0, 10)

    def result(seq, run, calls, poses):
        return RunResult(seq, "box", "faster", run, run, err, tmp_path / "x.h5", 1.0, 1.0,
                         {"pose_calls": calls, "poses": poses})

    lines = pose_warnings([result("a", "full", 10, 0), result("a", "pose", 10, 0),
                           result("b", "full", 10, 3), result("c", "full", 0, 0)])
    assert len(lines) == 1 and lines[0].startswith("warning: a:") and "10 frames" in lines[0]


def test_onnx_backend_finds_and_runs_the_exported_model(tiny_benchmark, tmp_path, capsys):
    """--backend onnxruntime finds the exported model by its embedded record, runs it on
    onnxruntime and tracks with its poses. (That an exported trained network decodes the
    poses torch does is ``tests/models/test_shipped_weights.py``'s: this random tiny network's
    flat maps are all near-ties, which no two backends break alike.) Its decoding thresholds
    are off so that it finds poses, and so is the depth check that would drop them."""
    pytest.importorskip("onnxruntime")
    from evtrack.eval.pose_setup import make_pose_source
    from evtrack.models import OnnxPoseEstimator, load_model
    from evtrack.models.onnx_export import export_onnx
    from evtrack.models.weights import set_record_decode

    pt = save_tiny_weights(tmp_path / "pt" / "box.pt")
    set_record_decode(pt, {"peak_threshold": 0.0, "min_affinity_norm": 0.0,
                           "max_angle_deg": 180.0, "min_confidence": 0.0})
    net, _ = load_model(pt)
    (tmp_path / "onnx" / "deep").mkdir(parents=True)
    onnx = export_onnx(net, tmp_path / "onnx" / "deep" / "box.onnx")
    save_tiny_weights(tmp_path / "onnx" / "can.pt", object_name="can")  # not an .onnx: ignored
    seq = Sequence.load(tiny_benchmark / "box_faster")
    spec = PoseSourceSpec("network", weights_dir=tmp_path / "onnx", backend="onnxruntime")
    assert resolve_weights(spec, ["box"]) == {"box": onnx}
    source = make_pose_source(spec, seq, onnx, threads=1)
    assert isinstance(source.estimator, OnnxPoseEstimator)
    assert source.estimator.session.get_session_options().intra_op_num_threads == 1
    assert source(int(seq.rgb_times_us[0]), seq.rgb(0), None) is not None
    config = tmp_path / "tracker.yaml"
    config.write_text(TINY_TRACKER_YAML + "pose_gate: {depth_min_share: 0.0}\n")
    out = tmp_path / "o"
    code = main(["evaluate", "--benchmark", str(tiny_benchmark / "box_faster"), "--weights-dir",
                 str(tmp_path / "onnx"), "--backend", "onnxruntime", "--config", str(config),
                 "--methods", "pose", "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr().err
    manifest = yaml.safe_load((out / "results.yaml").read_text())
    assert manifest["weights"]["box"] == str(onnx)
    assert "ONNX models per object" in (out / "results.md").read_text()
    stats = Trajectory.load(out / "trajectories" / "box_faster" / "pose.h5").meta["stats"]
    assert stats["poses"] > 0, stats


def test_backend_without_its_files_names_the_other(tiny_benchmark, tmp_path, capsys):
    save_tiny_weights(tmp_path / "w" / "box.pt")
    code = main(["evaluate", "--benchmark", str(tiny_benchmark), "--weights-dir",
                 str(tmp_path / "w"), "--backend", "onnxruntime", "--out", str(tmp_path / "o"),
                 "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "no .onnx pose-network files for object 'box'" in err
    assert "evtrack export pose" in err and not (tmp_path / "o").exists()
    assert main(["evaluate", "--benchmark", str(tiny_benchmark), "--oracle", "--backend",
                 "onnxruntime"]) == 1
    assert "not with --oracle" in capsys.readouterr().err


def test_results_folder_is_not_mixed_with_an_earlier_evaluation(tiny_benchmark,
                                                                 tiny_tracker_yaml, tmp_path,
                                                                 capsys):
    """A second evaluation into the same folder is refused without --overwrite (nothing
    changes); with it, the earlier evaluation's outputs go (a run it no longer has leaves no
    trajectory behind) and other files stay."""
    out = tmp_path / "res"
    bench = str(tiny_benchmark / "box_faster")
    common = ["evaluate", "--benchmark", bench, "--oracle", "--config", str(tiny_tracker_yaml),
              "--out", str(out), "--quiet"]
    assert main([*common, "--methods", "pose", "velocity"]) == 0
    (out / "notes.txt").write_text("mine")
    before = (out / "results.yaml").read_bytes()
    capsys.readouterr()
    assert main([*common, "--methods", "pose"]) == 1
    err = capsys.readouterr().err
    assert "holds the outputs of an earlier run" in err and "--overwrite" in err
    assert (out / "results.yaml").read_bytes() == before
    assert main([*common, "--methods", "pose", "--overwrite"]) == 0
    runs = {p.stem for p in (out / "trajectories" / "box_faster").glob("*.h5")}
    assert runs == {"pose"}
    manifest = yaml.safe_load((out / "results.yaml").read_text())
    assert [r["name"] for r in manifest["runs"]] == ["pose"]
    assert (out / "notes.txt").read_text() == "mine"


def test_failed_evaluation_leaves_nothing_behind(tiny_benchmark, tiny_tracker_yaml, tmp_path,
                                                 monkeypatch):
    import evtrack.eval.report as report

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(report, "write_report", broken)  # after every run was tracked
    out = tmp_path / "new" / "res"
    with pytest.raises(RuntimeError, match="disk full"):
        main(["evaluate", "--benchmark", str(tiny_benchmark / "box_faster"), "--oracle",
              "--config", str(tiny_tracker_yaml), "--methods", "pose", "--out", str(out),
              "--quiet"])
    assert not out.exists()
    # into an existing folder: its own files stay, the half-written evaluation goes
    keep = tmp_path / "kept"
    keep.mkdir()
    (keep / "notes.txt").write_text("mine")
    with pytest.raises(RuntimeError, match="disk full"):
        main(["evaluate", "--benchmark", str(tiny_benchmark / "box_faster"), "--oracle",
              "--config", str(tiny_tracker_yaml), "--methods", "pose", "--out", str(keep),
              "--quiet"])
    assert sorted(p.name for p in keep.iterdir()) == ["notes.txt"]


def test_overwrite_never_deletes_the_inputs(tiny_benchmark, tmp_path, capsys):
    """A benchmark folder that lies where the evaluation writes (here under ``videos/``) is an
    error, with or without --overwrite, and stays whole."""
    w = tmp_path / "w"
    shutil.copytree(tiny_benchmark / "box_faster", w / "videos" / "box_faster")
    before = sorted(p.relative_to(w) for p in w.rglob("*"))
    for extra in ([], ["--overwrite"]):
        assert main(["evaluate", "--benchmark", str(w / "videos"), "--oracle", "--methods",
                     "pose", "--out", str(w), "--quiet", *extra]) == 1
        assert "lies in" in capsys.readouterr().err
    assert sorted(p.relative_to(w) for p in w.rglob("*")) == before


def test_onnx_problems_show_before_any_tracking(tiny_benchmark, tmp_path, capsys):
    """A model whose record reads but whose graph is broken is named before the runs; with
    --oracle-where-missing, weights that run on the other backend are an error, not a gap
    silently filled by the oracle."""
    pytest.importorskip("onnxruntime")
    import onnx

    from evtrack.models import load_model
    from evtrack.models.onnx_export import export_onnx

    net, _ = load_model(save_tiny_weights(tmp_path / "pt" / "box.pt"))
    (tmp_path / "onnx").mkdir()
    good = export_onnx(net, tmp_path / "onnx" / "box.onnx")
    proto = onnx.load(str(good))
    del proto.graph.node[len(proto.graph.node) // 2]  # the record stays, the graph breaks
    onnx.save(proto, str(good))
    out = tmp_path / "o"
    assert main(["evaluate", "--benchmark", str(tiny_benchmark / "box_faster"), "--weights-dir",
                 str(tmp_path / "onnx"), "--backend", "onnxruntime", "--methods", "pose",
                 "--out", str(out), "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "onnxruntime cannot load the model" in captured.err and "box.onnx" in captured.err
    assert "evaluating" not in captured.out and not out.exists()
    assert main(["evaluate", "--benchmark", str(tiny_benchmark / "box_faster"), "--weights-dir",
                 str(tmp_path / "pt"), "--backend", "onnxruntime", "--oracle-where-missing",
                 "--methods", "pose", "--out", str(out), "--quiet"]) == 1
    assert "pass --backend torch" in capsys.readouterr().err and not out.exists()


def test_rotation_notes_name_the_unobserved_axes(tmp_path):
    """evaluate notes each run whose frame alignments left a rotation unobserved (its
    trajectory's ``meta["rotations"]``), and nothing for the others."""
    from evtrack.eval.benchmark import RunResult, rotation_notes
    from evtrack.eval.metrics import TrackingErrors

    err = TrackingErrors(1.0, 0.5, 2.0, 1.0, 10, 10)
    unseen = {"alignments": {"depth": 30},
              "unobserved": [{"axis": [-0.0014, 1.0, 0.0007], "std_deg": {"depth": 4.83}}]}
    seen = {"alignments": {"depth": 30, "appearance": 10}, "unobserved": []}
    results = [RunResult(seq, "can", "faster", "full", "full", err, tmp_path / "x.h5", 1.0,
                         1.0, {}, rotations=rotations)
               for seq, rotations in (("a", unseen), ("b", seen), ("c", {}))]
    assert rotation_notes(results) == [
        "note: a (full): the frame alignments did not observe the rotation about the object's "
        "axis (+0.00, +1.00, +0.00): depth ±4.8°"]


def test_pose_latency_flag_sets_when_poses_reach_the_filter(evaluated, tiny_benchmark,
                                                             tiny_tracker_yaml, tmp_path):
    """--pose-latency-ms 0 runs each sequence as its config with pose_latency_ms 0 would (the
    same trajectory as run_one with that config), records it in results.yaml, and differs from
    the config's own latency."""
    base = TrackerConfig.from_yaml(tiny_tracker_yaml)
    assert base.pose_latency_ms > 0
    out = tmp_path / "results"
    assert main(["evaluate", "--benchmark", str(tiny_benchmark / "box_faster"), "--oracle",
                 "--config", str(tiny_tracker_yaml), "--methods", "pose",
                 "--pose-latency-ms", "0", "--out", str(out), "--quiet"]) == 0
    manifest = yaml.safe_load((out / "results.yaml").read_text())
    assert manifest["tracker_config"]["pose_latency_ms"] == 0.0
    got = Trajectory.load(out / "trajectories" / "box_faster" / "pose.h5")
    seqs = find_sequences(tiny_benchmark / "box_faster")
    ref = run_one(seqs[0], run_specs(["pose"])[0], base.replace(pose_latency_ms=0.0),
                  PoseSourceSpec("oracle"), None, tmp_path / "ref")
    expected = Trajectory.load(ref.trajectory)
    assert np.array_equal(got.poses.numpy(), expected.poses.numpy(), equal_nan=True)
    late = Trajectory.load(evaluated / "trajectories" / "box_faster" / "pose.h5")
    assert not np.array_equal(got.poses.numpy(), late.poses.numpy(), equal_nan=True)


def test_a_negative_pose_latency_is_refused(tiny_benchmark, capsys):
    assert main(["evaluate", "--benchmark", str(tiny_benchmark), "--oracle",
                 "--pose-latency-ms", "-5"]) == 1
    assert "--pose-latency-ms must be finite and >= 0, got -5.0" in capsys.readouterr().err
