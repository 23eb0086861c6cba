"""Benchmark tables: numbers against plain numpy computations, Markdown and CSV layout."""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from evtrack.eval.metrics import TrackingErrors, error_summary
from evtrack.eval.pose_auc import PoseScores
from evtrack.eval.tables import (
    CSV_COLUMNS,
    Cell,
    average_rows,
    csv_table,
    markdown_tables,
    write_tables,
)


@dataclass
class Entry:
    sequence: str
    object_name: str
    speed: str
    run: str
    errors: TrackingErrors
    scores: PoseScores | None = None


SEQUENCES = [("obj_a_regular", "obj_a", "regular"), ("obj_a_faster", "obj_a", "faster"),
             ("obj_b_regular", "obj_b", "regular"), ("obj_b_faster", "obj_b", "faster")]
RUNS = ["full", "pose", "full-no-weighting"]


def make_entries(seed: int = 0):
    """Entries from random per-sample errors, and the samples (cm, deg) per (sequence, run)."""
    rng = np.random.default_rng(seed)
    entries, samples = [], {}
    for name, obj, speed in SEQUENCES:
        for run in RUNS:
            n = int(rng.integers(50, 200))
            p_cm = np.abs(rng.normal(2.0, 1.0, n))
            r_deg = np.abs(rng.normal(8.0, 3.0, n))
            err = error_summary(torch.from_numpy(p_cm / 100.0), torch.from_numpy(np.deg2rad(r_deg)),
                                total=n + 10)
            entries.append(Entry(name, obj, speed, run, err))
            samples[(name, run)] = (p_cm, r_deg, n)
    return entries, samples


def rmse(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x ** 2)))


def read_csv(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def test_cell_text():
    assert Cell(1.954, 1.0949).text() == "1.95 ± 1.09"
    assert Cell(12.0, 3.0).text(1) == "12.0 ± 3.0"
    assert Cell(math.nan, 1.0).text() == "—"


def test_csv_sequence_rows_match_numpy():
    entries, samples = make_entries()
    rows = read_csv(csv_table(entries, RUNS))
    seq_rows = [r for r in rows if r["table"] == "sequence"]
    assert len(seq_rows) == len(SEQUENCES) * len(RUNS)
    for r in seq_rows:
        p, q, n = samples[(r["sequence"], r["run"])]
        assert float(r["position_rmse_cm"]) == pytest.approx(rmse(p), rel=1e-9)
        assert float(r["position_std_cm"]) == pytest.approx(p.std(), rel=1e-9)
        assert float(r["rotation_rmse_deg"]) == pytest.approx(rmse(q), rel=1e-9)
        assert float(r["rotation_std_deg"]) == pytest.approx(q.std(), rel=1e-9)
        assert int(r["samples"]) == n and int(r["total"]) == n + 10
        assert float(r["tracked_fraction"]) == pytest.approx(n / (n + 10))


def test_csv_averages_are_means_of_the_sequences():
    entries, samples = make_entries(1)
    rows = read_csv(csv_table(entries, RUNS))
    avg = {(r["run"], r["speed"]): r for r in rows if r["table"] == "average"}
    assert set(avg) == {(run, s) for run in RUNS for s in ("regular", "faster", "all")}
    for run in RUNS:
        for speed in ("regular", "faster", "all"):
            names = [n for n, _, s in SEQUENCES if speed in ("all", s)]
            r = avg[(run, speed)]
            p = [samples[(n, run)][0] for n in names]
            q = [samples[(n, run)][1] for n in names]
            assert float(r["position_rmse_cm"]) == pytest.approx(np.mean([rmse(x) for x in p]))
            assert float(r["position_std_cm"]) == pytest.approx(np.mean([x.std() for x in p]))
            assert float(r["rotation_rmse_deg"]) == pytest.approx(np.mean([rmse(x) for x in q]))
            assert float(r["rotation_std_deg"]) == pytest.approx(np.mean([x.std() for x in q]))
            assert int(r["sequences"]) == len(names)
            assert int(r["samples"]) == sum(samples[(n, run)][2] for n in names)


def test_markdown_layout_and_cells():
    entries, samples = make_entries(2)
    text = markdown_tables(entries, ["full", "pose"], {"full": "Ours (OF)"},
                           ablations=["full-no-weighting"], caption="ORACLE test")
    assert "Pose source: ORACLE test" in text
    lines = text.splitlines()
    header = next(ln for ln in lines if ln.startswith("| object"))
    assert "Ours (OF) e_p (cm)" in header and "pose e_r (deg)" in header
    # the row of obj_b faster: cells in column order
    row = next(ln for ln in lines if ln.startswith("| obj_b | faster"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    p, q, _ = samples[("obj_b_faster", "full")]
    assert cells[2] == f"{rmse(p):.2f} ± {p.std():.2f}"
    assert cells[3] == f"{rmse(q):.2f} ± {q.std():.2f}"
    p, q, _ = samples[("obj_b_faster", "pose")]
    assert cells[4] == f"{rmse(p):.2f} ± {p.std():.2f}"
    # average over all sequences of the full method
    row = next(ln for ln in lines if ln.startswith("| **average** | all"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    ps = [samples[(n, "full")][0] for n, _, _ in SEQUENCES]
    mean_rmse, mean_std = np.mean([rmse(x) for x in ps]), np.mean([x.std() for x in ps])
    assert cells[2] == f"{mean_rmse:.2f} ± {mean_std:.2f}"
    # Table III has the full method and the ablation; Table I does not show the ablation
    assert "## Table III" in text
    table_one = text.split("## Tracked samples")[0]
    assert "full-no-weighting" not in table_one
    table_three = text.split("## Table III")[1]
    assert "| Ours (OF) |" in table_three and "| full-no-weighting |" in table_three


def test_no_ablation_table_without_ablations():
    entries, _ = make_entries()
    assert "Table III" not in markdown_tables(entries, ["full", "pose"])


def test_untracked_sequence_makes_its_averages_undefined():
    entries, _ = make_entries()
    nan = math.nan
    entries[0] = Entry(entries[0].sequence, entries[0].object_name, entries[0].speed,
                       entries[0].run, TrackingErrors(nan, nan, nan, nan, 0, 100))
    run, speed = entries[0].run, entries[0].speed
    avgs = {(a.run, a.speed): a for a in average_rows(entries, RUNS)}
    assert math.isnan(avgs[(run, speed)].position.rmse)
    assert math.isnan(avgs[(run, "all")].rotation.rmse)
    other = "faster" if speed == "regular" else "regular"
    assert math.isfinite(avgs[(run, other)].position.rmse)
    text = markdown_tables(entries, RUNS[:2])
    assert "—" in text
    rows = read_csv(csv_table(entries, RUNS))
    first = next(r for r in rows if r["table"] == "sequence" and r["sequence"] == SEQUENCES[0][0]
                 and r["run"] == run)
    assert first["position_rmse_cm"] == "nan" and first["samples"] == "0"


def test_repeated_object_and_speed_are_told_apart():
    entries, _ = make_entries()
    extra = Entry("other/obj_a_regular", "obj_a", "regular", "full", entries[0].errors)
    text = markdown_tables([*entries, extra], ["full"])
    assert "| obj_a (other/obj_a_regular) | regular |" in text
    assert "| obj_a (obj_a_regular) | regular |" in text


def test_write_tables_writes_both_files(tmp_path):
    entries, _ = make_entries()
    text = write_tables(entries, tmp_path / "res", ["full", "pose"],
                        ablations=["full-no-weighting"])
    assert (tmp_path / "res" / "results.md").read_text() == text
    rows = read_csv((tmp_path / "res" / "results.csv").read_text())
    assert {r["run"] for r in rows} == {"full", "pose", "full-no-weighting"}
    assert not [p for p in (tmp_path / "res").iterdir() if p.name.startswith(".")]


def with_scores(entries, seed: int = 0):
    """The entries with random pose scores; the scores per (sequence, run)."""
    rng = np.random.default_rng(seed)
    out, scores = [], {}
    for e in entries:
        add, adds, within = rng.uniform(0, 100, 3)
        diameter = {"obj_a": 0.2, "obj_b": 0.12}[e.object_name]
        s = PoseScores(add, max(add, adds), within, diameter, e.errors.total, e.errors.samples,
                       500)
        out.append(Entry(e.sequence, e.object_name, e.speed, e.run, e.errors, s))
        scores[(e.sequence, e.run)] = s
    return out, scores


def cells_of(line: str) -> list[str]:
    return [c.strip() for c in line.strip("|").split("|")]


def test_csv_carries_the_pose_scores_and_their_averages():
    entries, scores = with_scores(make_entries()[0])
    rows = read_csv(csv_table(entries, RUNS))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert list(CSV_COLUMNS[-4:]) == ["add_auc_pct", "adds_auc_pct", "within_5cm_5deg_pct",
                                      "diameter_cm"]
    for r in (r for r in rows if r["table"] == "sequence"):
        s = scores[(r["sequence"], r["run"])]
        assert float(r["add_auc_pct"]) == pytest.approx(s.add_auc)
        assert float(r["adds_auc_pct"]) == pytest.approx(s.adds_auc)
        assert float(r["within_5cm_5deg_pct"]) == pytest.approx(s.within_5cm_5deg)
        assert float(r["diameter_cm"]) == pytest.approx(100 * s.diameter_m)
    for r in (r for r in rows if r["table"] == "average"):
        names = [n for n, _, sp in SEQUENCES if r["speed"] in ("all", sp)]
        mine = [scores[(n, r["run"])] for n in names]
        assert float(r["add_auc_pct"]) == pytest.approx(np.mean([s.add_auc for s in mine]))
        assert float(r["adds_auc_pct"]) == pytest.approx(np.mean([s.adds_auc for s in mine]))
        assert float(r["within_5cm_5deg_pct"]) == pytest.approx(
            np.mean([s.within_5cm_5deg for s in mine]))
        assert r["diameter_cm"] == "nan"
    # entries without scores: NaN there, the RMSE columns as before
    plain = read_csv(csv_table(make_entries()[0], RUNS))
    assert all(r["add_auc_pct"] == "nan" for r in plain)
    for a, b in zip(plain, rows, strict=True):
        assert [a[c] for c in CSV_COLUMNS[:14]] == [b[c] for c in CSV_COLUMNS[:14]]


def test_markdown_pose_accuracy_table_and_average_columns():
    entries, scores = with_scores(make_entries(2)[0], seed=1)
    plain = markdown_tables(make_entries(2)[0], ["full", "pose"], {"full": "Ours (OF)"},
                            ablations=["full-no-weighting"])
    text = markdown_tables(entries, ["full", "pose"], {"full": "Ours (OF)"},
                           ablations=["full-no-weighting"])
    section = text.split("## Pose accuracy")[1].split("## Table II")[0]
    assert "up to 10 % of the diameter" in section and "5 cm / 5°" in section
    lines = section.splitlines()
    head = cells_of(next(ln for ln in lines if ln.startswith("| object")))
    assert head == ["object", "speed", "d (cm)", "Ours (OF) ADD", "Ours (OF) ADD-S",
                    "Ours (OF) 5cm/5°", "pose ADD", "pose ADD-S", "pose 5cm/5°"]
    row = cells_of(next(ln for ln in lines if ln.startswith("| obj_b | faster")))
    s = scores[("obj_b_faster", "full")]
    q = scores[("obj_b_faster", "pose")]
    assert row[2:] == ["12.0", f"{s.add_auc:.1f}", f"{s.adds_auc:.1f}",
                       f"{s.within_5cm_5deg:.1f}", f"{q.add_auc:.1f}", f"{q.adds_auc:.1f}",
                       f"{q.within_5cm_5deg:.1f}"]
    row = cells_of(next(ln for ln in lines if ln.startswith("| **average** | all")))
    assert row[3] == f"{np.mean([scores[(n, 'full')].add_auc for n, _, _ in SEQUENCES]):.1f}"
    # Table II and III: the RMSE columns as without scores, then the scores per speed group
    for title in ("## Table II", "## Table III"):
        new = text.split(title)[1].split("\n## ")[0].splitlines()
        old = plain.split(title)[1].split("\n## ")[0].splitlines()
        groups = ("regular", "faster", "all")
        head = cells_of(next(ln for ln in new if ln.startswith("| run")))
        assert head == ["run", *[f"{g} {e}" for g in groups for e in ("e_p (cm)", "e_r (deg)")],
                        *[f"{g} {h}" for g in groups for h in ("ADD", "ADD-S", "5cm/5°")]]
        new_full = cells_of(next(ln for ln in new if ln.startswith("| Ours (OF)")))
        old_full = cells_of(next(ln for ln in old if ln.startswith("| Ours (OF)")))
        assert new_full[:7] == old_full[:7] and old_full[7:] == ["—"] * 9
        all_add = np.mean([scores[(n, "full")].adds_auc for n, _, _ in SEQUENCES])
        assert new_full[-2] == f"{all_add:.1f}"
    # the tables before the new one are unchanged
    assert text.split("## Pose accuracy")[0] == plain.split("## Pose accuracy")[0]


def test_missing_scores_show_a_dash_and_the_reason_once():
    entries, _ = with_scores(make_entries()[0])
    note = "the sequence names no object mesh (meta.yaml object.mesh)"
    entries = [Entry(e.sequence, e.object_name, e.speed, e.run, e.errors,
                     PoseScores.unavailable(e.errors.total, note))
               if e.sequence == "obj_a_faster" else e for e in entries]
    text = markdown_tables(entries, ["full", "pose"])
    section = text.split("## Pose accuracy")[1].split("## Table II")[0]
    row = cells_of(next(ln for ln in section.splitlines() if ln.startswith("| obj_a | faster")))
    assert row[2:] == ["—"] * 7
    assert section.count(note) == 1 and "obj_a_faster" in section
    avgs = {(a.run, a.speed): a for a in average_rows(entries, RUNS)}
    assert math.isnan(avgs[("full", "faster")].add_auc)
    assert math.isnan(avgs[("full", "all")].within_5cm_5deg)
    assert math.isfinite(avgs[("full", "regular")].adds_auc)


@dataclass
class PlacedEntry(Entry):
    split: str = "test"
    replicate: int | None = None


def test_seed_spread_against_a_direct_computation() -> None:
    from evtrack.eval.tables import ALL, seed_spreads

    rng = np.random.default_rng(3)
    entries = []
    for obj in ("a", "b"):
        for speed in ("regular", "faster"):
            for k in range(3):
                p, r = rng.uniform(0.5, 5.0), rng.uniform(2.0, 20.0)
                err = TrackingErrors(p, 0.1, r, 0.2, 10, 10)
                entries.append(PlacedEntry(f"{obj}_{speed}_{k}", obj, speed, "full", err,
                                           replicate=k))
    spreads = {(s.run, s.speed): s for s in seed_spreads(entries, ["full", "absent"])}
    assert set(spreads) == {("full", "regular"), ("full", "faster"), ("full", ALL)}
    for (_, speed), sp in spreads.items():
        group = [e for e in entries if speed == ALL or e.speed == speed]
        per_k = [np.mean([e.errors.rotation_rmse_deg for e in group if e.replicate == k])
                 for k in range(3)]
        assert sp.replicates == (0, 1, 2) and sp.split == "test"
        np.testing.assert_allclose(sp.rotation, per_k)
        d = sp.to_dict()["rotation_deg"]
        np.testing.assert_allclose([d["mean"], d["sd"], d["min"], d["max"]],
                                   [np.mean(per_k), np.std(per_k, ddof=1), min(per_k),
                                    max(per_k)])
        assert sp.text(sp.rotation) == (f"{np.mean(per_k):.2f} ± {np.std(per_k, ddof=1):.2f} "
                                        f"[{min(per_k):.2f}, {max(per_k):.2f}]")
    md = markdown_tables(entries, ["full"])
    assert "## Spread over seeds (test split)" in md
    assert "| full | faster | 3 |" in md


def test_seed_spread_is_absent_outside_a_split_and_plain_for_one_seed() -> None:
    from evtrack.eval.tables import seed_spreads

    entries, _ = make_entries()
    assert seed_spreads(entries, RUNS) == []
    assert "Spread over seeds" not in markdown_tables(entries, ["full"])
    err = TrackingErrors(1.5, 0.1, 7.25, 0.2, 10, 10)
    one = [PlacedEntry("s", "o", "faster", "full", err, replicate=0)]
    sp = seed_spreads(one, ["full"])[0]
    assert sp.text(sp.rotation) == "7.25" and math.isnan(sp.to_dict()["rotation_deg"]["sd"])
