"""The one-command YCB recipe (``scripts/train_ycb_parallel.sh``), end to end at a tiny scale.

The recipe's real run trains each object for two hours; here two objects train for a few
seconds each on 4 renders of their textured meshes, which is enough to show that the command
renders the shared YCB meshes, starts from the shipped coded-box network, runs the objects in
parallel and writes a loadable weights file and a model card per object.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from evtrack.models import load_model

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "train_ycb_parallel.sh"
OBJECTS = ("003_cracker_box", "010_potted_meat_can")


def _run_recipe(tmp_path: Path, objects: str, *extra: str) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    # `evtrack` of this interpreter's environment, also when the venv is not activated (CI)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.update(OBJECTS=objects, CORES="2", MAX_TIME="00:00:00:05",
               LOG_DIR=str(tmp_path / "logs"))
    return subprocess.run(["bash", str(SCRIPT), *extra], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=600)


def test_recipe_trains_each_object_into_loadable_weights_and_a_card(tmp_path, ycb_dir, gl):
    configs = " ".join(f"configs/pose_ycb_{name}.yaml" for name in OBJECTS)
    out = _run_recipe(
        tmp_path, configs,
        "--set", "data.train_samples=4", "--set", "data.val_samples=2",
        "--set", "data.batch_size=2", "--set", f"data.cache_dir={tmp_path / 'cache'}",
        "--set", f"output_dir={tmp_path / 'runs'}", "--set", "trainer.check_val_every_n_epoch=1",
        "--set", "optim.warmup_steps=1")
    assert out.returncode == 0, out.stdout + out.stderr
    for name in OBJECTS:
        assert f"pose_ycb_{name}: done" in out.stdout
        # CORES split between the two runs: one core each, no extra loader workers
        assert f"pose_ycb_{name}: 1 cores, max_time 00:00:00:05" in out.stdout
        run = tmp_path / "runs" / f"{name}_dope_lite_small"
        weights = run / f"{name}_dope_lite_small.pt"
        net, record = load_model(weights)
        assert record.object_name == name and record.arch == "dope_lite_small"
        assert (run / f"{name}_dope_lite_small.md").read_text().strip()
        log = (tmp_path / "logs" / f"pose_ycb_{name}.log").read_text()
        assert str(weights) in log
        assert any((tmp_path / "cache").glob("train_*/shard_*.h5"))


def test_recipe_reports_a_failed_run_and_exits_non_zero(tmp_path):
    out = _run_recipe(tmp_path, "configs/pose_ycb_no_such_object.yaml")
    assert out.returncode != 0
    assert "pose_ycb_no_such_object: FAILED, see" in out.stderr
    assert "pose_ycb_no_such_object.yaml" in out.stderr  # the run's log tail names the file
