"""The held-out protocol of the benchmark set: disjoint seeds, folders, meta and the CLI."""

from __future__ import annotations

import pytest
import yaml

from evtrack.cli import main
from evtrack.sequence import Sequence
from evtrack.sim.benchmark_set import (
    BENCHMARK_SEEDS,
    MAX_SEEDS,
    PRESETS,
    BenchmarkEntry,
    split_entries,
    split_seed,
)
from evtrack.sim.objects import YCB_OBJECTS


def test_splits_share_no_seed_at_any_size() -> None:
    tuning = split_entries("tuning", MAX_SEEDS)
    test = split_entries("test", MAX_SEEDS)
    seeds_tuning = [e.seed for e in tuning]
    seeds_test = [e.seed for e in test]
    assert len(set(seeds_tuning)) == len(tuning) == MAX_SEEDS * len(YCB_OBJECTS) * len(PRESETS)
    assert len(set(seeds_test)) == len(test)
    assert not set(seeds_tuning) & set(seeds_test)
    assert len({e.folder_name for e in tuning + test}) == len(tuning) + len(test)


def test_fixed_set_is_the_tuning_splits_first_seed() -> None:
    first = {(e.object_name, e.preset): e.seed for e in split_entries("tuning", 1)}
    assert first == BENCHMARK_SEEDS


def test_split_entries_cover_every_cell_with_each_replicate() -> None:
    entries = split_entries("test", 3)
    cells = {(e.object_name, e.preset) for e in entries}
    assert cells == {(o, p) for o in YCB_OBJECTS for p in PRESETS}
    for cell in cells:
        assert sorted(e.replicate for e in entries if (e.object_name, e.preset) == cell) \
            == [0, 1, 2]
    e = entries[0]
    assert e.folder_name == f"{e.object_name}_{e.preset}_seed{e.seed}"
    assert e.describe() == {"split": "test", "replicate": 0, "seed": e.seed, "seeds": 3}
    assert BenchmarkEntry("a", "regular", 7).folder_name == "a_regular"


@pytest.mark.parametrize("args, match", [
    (("validation", 0, 0, 0), "unknown split"),
    (("test", 0, 0, MAX_SEEDS), "replicate"),
    (("test", 10, 0, 0), "index"),
    (("tuning", 0, -1, 0), "index"),
])
def test_split_seed_rejects_bad_arguments(args, match) -> None:
    with pytest.raises(ValueError, match=match):
        split_seed(*args)


def test_split_entries_rejects_bad_seed_counts() -> None:
    for bad in (0, MAX_SEEDS + 1):
        with pytest.raises(ValueError, match="seeds per cell"):
            split_entries("tuning", bad)


def test_cli_simulates_a_split_part_with_its_place_in_meta(tmp_path, ycb_dir, capsys) -> None:
    out = tmp_path / "test_split"
    args = ["simulate-benchmark", "--out", str(out), "--duration", "0.03", "--width", "64",
            "--height", "48", "--objects", "005_tomato_soup_can", "--presets", "faster",
            "--split", "test", "--seeds", "2", "--replicates", "1", "--ycb-dir", str(ycb_dir),
            "--quiet"]
    assert main(args) == 0
    seed = split_seed("test", YCB_OBJECTS.index("005_tomato_soup_can"), 1, 1)
    name = f"005_tomato_soup_can_faster_seed{seed}"
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == [name]
    seq = Sequence.load(out / name)
    assert seq.meta.extra["benchmark"] == {"split": "test", "replicate": 1, "seed": seed,
                                           "seeds": 2}
    assert seq.meta.extra["seed"] == seed
    row = yaml.safe_load((out / "summary.yaml").read_text())["sequences"][name]
    assert (row["split"], row["replicate"], row["seed"]) == ("test", 1, seed)
    assert name in capsys.readouterr().out


@pytest.mark.parametrize("extra, message", [
    (["--seeds", "2"], "--seeds needs --split"),
    (["--replicates", "0"], "--replicates needs --split"),
    (["--split", "test", "--seeds", "0"], "--seeds must be in 1.."),
    (["--split", "test", "--seeds", "2", "--replicates", "2"], "replicates 0..1"),
])
def test_cli_rejects_inconsistent_split_options(tmp_path, capsys, extra, message) -> None:
    out = tmp_path / "x"
    assert main(["simulate-benchmark", "--out", str(out), "--velocity-only", *extra]) == 1
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_velocity_report_of_a_split_names_its_folders(tmp_path, ycb_dir) -> None:
    out = tmp_path / "v"
    assert main(["simulate-benchmark", "--out", str(out), "--velocity-only", "--duration", "0.2",
                 "--split", "tuning", "--seeds", "2", "--objects", "cracker_box",
                 "--ycb-dir", str(ycb_dir)]) == 0
    rows = yaml.safe_load((out / "summary.yaml").read_text())["sequences"]
    assert sorted(rows) == sorted(e.folder_name for e in split_entries("tuning", 2)
                                  if e.object_name == "003_cracker_box")
    assert {r["replicate"] for r in rows.values()} == {0, 1}


def test_simulate_rejects_extra_meta_that_replaces_its_own(tmp_path, ycb_dir) -> None:
    from evtrack.sim.config import SimConfig
    from evtrack.sim.engine import simulate
    from evtrack.sim.objects import resolve_object

    obj = resolve_object("005_tomato_soup_can", ycb_dir=ycb_dir)
    with pytest.raises(ValueError, match=r"\['seed'\]"):
        simulate(obj, SimConfig(duration=0.01), tmp_path / "s", extra={"seed": 3})
    assert not (tmp_path / "s").exists()
