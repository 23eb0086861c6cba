"""Benchmark tables like the method paper's Tables I–III, as Markdown and CSV.

Input: one entry per (sequence, run) with the attributes ``sequence``, ``object_name``,
``speed``, ``run``, ``errors`` (:class:`~evtrack.eval.metrics.TrackingErrors`) and, optionally,
``scores`` (:class:`~evtrack.eval.pose_auc.PoseScores`; an entry without it, or with ``None``,
shows ``—`` there), e.g. :class:`~evtrack.eval.benchmark.RunResult`.

* Table I: rows = sequences (object x speed), then averages per speed and over all sequences;
  columns = runs; cells ``RMSE ± σ`` of the position error (cm) and the rotation error (deg).
* Tracked samples: the share of each trajectory the RMSE is taken over (the rest is before the
  first pose or while the object was lost).
* Pose accuracy: rows as Table I, with the object's diameter ``d`` (cm); per run the ADD AUC
  and the ADD-S AUC (%, thresholds from 0 to 10 % of ``d``) and the share of samples within
  5 cm and 5° (%), over every ground-truth sample of each sequence, the untracked ones failing
  (:mod:`evtrack.eval.pose_auc`). Then one line per sequence whose scores could not be
  computed, saying why.
* Table II: the averages only (rows = runs, columns = speeds): the RMSEs, then the ADD AUC,
  ADD-S AUC and 5 cm / 5° share per speed.
* Table III (ablation): the full method against its ablations, averaged, as Table II.
* Spread over seeds (sequences of a split of the held-out protocol, see
  :mod:`evtrack.sim.benchmark_set`): per run and speed, the average of each seed replicate
  (the mean RMSE over that replicate's sequences), then their mean, sample standard deviation
  and range: how much of an average is one set of seeds' luck.

Conventions: σ is the population standard deviation of a sequence's per-sample errors
(:func:`~evtrack.eval.metrics.error_summary`). An average is the arithmetic mean of the
per-sequence RMSEs (the paper's Table II averages them this way) and of the per-sequence σs;
it is undefined (``—``, NaN in the CSV) when any of its sequences has no tracked sample. The
averages of the AUCs and of the 5 cm / 5° share are the means of the per-sequence values too,
undefined when any of its sequences has none (no mesh); a sequence tracked nowhere scores 0.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from evtrack.eval.metrics import TrackingErrors
from evtrack.eval.pose_auc import PoseScores
from evtrack.eval.sequences import SPEEDS

__all__ = ["ErrorEntry", "Cell", "AverageRow", "SeedSpread", "average_rows", "seed_spreads",
           "markdown_tables", "csv_table", "write_tables", "ALL"]

ALL = "all"
"""The speed group of the averages over every sequence."""

CSV_COLUMNS = ("table", "sequence", "object", "speed", "run", "label", "position_rmse_cm",
               "position_std_cm", "rotation_rmse_deg", "rotation_std_deg", "samples", "total",
               "tracked_fraction", "sequences", "add_auc_pct", "adds_auc_pct",
               "within_5cm_5deg_pct", "diameter_cm")
"""Columns of ``results.csv``: ``*_pct`` are the ADD / ADD-S AUC and the 5 cm / 5° share (%);
``diameter_cm`` is the object's diameter (NaN in the average rows)."""


class ErrorEntry(Protocol):
    """What the tables read from each (sequence, run) result (and ``scores``, a
    :class:`~evtrack.eval.pose_auc.PoseScores` or ``None``, where the entry has it)."""

    sequence: str
    object_name: str
    speed: str
    run: str
    errors: TrackingErrors


@dataclass(frozen=True)
class Cell:
    """An ``RMSE ± σ`` pair (cm or deg)."""

    rmse: float
    std: float

    def text(self, digits: int = 2) -> str:
        if not (math.isfinite(self.rmse) and math.isfinite(self.std)):
            return "—"
        return f"{self.rmse:.{digits}f} ± {self.std:.{digits}f}"


@dataclass(frozen=True)
class AverageRow:
    """The average of one run over a group of sequences.

    Attributes:
        run: the run's name; speed: the group (a speed, or :data:`ALL`).
        position, rotation: mean RMSE and mean σ (cm, deg).
        samples, total: tracked and all samples summed over the group.
        sequences: sequences averaged.
        add_auc, adds_auc, within_5cm_5deg: means of the per-sequence ADD AUC, ADD-S AUC and
            5 cm / 5° share (%), NaN where a sequence has none.
    """

    run: str
    speed: str
    position: Cell
    rotation: Cell
    samples: int
    total: int
    sequences: int
    add_auc: float = math.nan
    adds_auc: float = math.nan
    within_5cm_5deg: float = math.nan


def _speed_groups(entries: Sequence[ErrorEntry]) -> list[str]:
    speeds = {e.speed for e in entries}
    ordered = [s for s in SPEEDS if s in speeds]
    ordered += sorted(s for s in speeds if s not in SPEEDS)
    return ordered


def _mean(values: list[float]) -> float:
    if not values or not all(math.isfinite(v) for v in values):
        return math.nan
    return sum(values) / len(values)


def _scores(entry: ErrorEntry) -> PoseScores | None:
    return getattr(entry, "scores", None)


def _score_values(entry: ErrorEntry) -> tuple[float, float, float]:
    """(ADD AUC, ADD-S AUC, 5 cm / 5° share) in %, NaN where not measured."""
    s = _scores(entry)
    if s is None:
        return math.nan, math.nan, math.nan
    return s.add_auc, s.adds_auc, s.within_5cm_5deg


def _average(run: str, speed: str, group: list[ErrorEntry]) -> AverageRow:
    errs = [e.errors for e in group]
    add, adds, within = zip(*(_score_values(e) for e in group), strict=True)
    return AverageRow(
        run, speed,
        Cell(_mean([x.position_rmse_cm for x in errs]), _mean([x.position_std_cm for x in errs])),
        Cell(_mean([x.rotation_rmse_deg for x in errs]), _mean([x.rotation_std_deg for x in errs])),
        sum(x.samples for x in errs), sum(x.total for x in errs), len(errs),
        _mean(list(add)), _mean(list(adds)), _mean(list(within)))


def average_rows(entries: Sequence[ErrorEntry], runs: Sequence[str]) -> list[AverageRow]:
    """Averages of each run per speed group and over all sequences (run-major order)."""
    rows = []
    groups = _speed_groups(entries)
    for run in runs:
        mine = [e for e in entries if e.run == run]
        if not mine:
            continue
        for speed in groups:
            rows.append(_average(run, speed, [e for e in mine if e.speed == speed]))
        rows.append(_average(run, ALL, mine))
    return rows


@dataclass(frozen=True)
class SeedSpread:
    """How the average of one run over one speed group varies with the seeds.

    Attributes:
        run, speed: as :class:`AverageRow`; split: the entries' split (``"tuning"``/``"test"``).
        position, rotation: the per-replicate averages of the RMSEs (cm, deg), in replicate
            order (a replicate's average is the mean over its sequences of the group).
        replicates: the replicate indices.
    """

    run: str
    speed: str
    split: str
    replicates: tuple[int, ...]
    position: tuple[float, ...]
    rotation: tuple[float, ...]

    @staticmethod
    def _stats(values: tuple[float, ...]) -> tuple[float, float, float, float]:
        """(mean, sample sd (NaN for one value), min, max); NaN if any value is."""
        if not values or not all(math.isfinite(v) for v in values):
            return (math.nan,) * 4
        mean = sum(values) / len(values)
        sd = (math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))
              if len(values) > 1 else math.nan)
        return mean, sd, min(values), max(values)

    def text(self, values: tuple[float, ...]) -> str:
        """``mean ± sd [min, max]`` (``mean`` alone for one replicate; ``—`` if undefined)."""
        mean, sd, lo, hi = self._stats(values)
        if not math.isfinite(mean):
            return "—"
        if not math.isfinite(sd):
            return f"{mean:.2f}"
        return f"{mean:.2f} ± {sd:.2f} [{lo:.2f}, {hi:.2f}]"

    def to_dict(self) -> dict:
        out: dict = {"run": self.run, "speed": self.speed, "split": self.split,
                     "replicates": list(self.replicates)}
        for name, values in (("position_cm", self.position), ("rotation_deg", self.rotation)):
            mean, sd, lo, hi = self._stats(values)
            out[name] = {"per_replicate": list(values), "mean": mean, "sd": sd, "min": lo,
                         "max": hi}
        return out


def seed_spreads(entries: Sequence[ErrorEntry], runs: Sequence[str]) -> list[SeedSpread]:
    """Per run and speed group (and over all), the averages of each seed replicate.

    Only entries with a ``replicate`` (sequences of a split) count; empty when there are none.
    """
    placed = [e for e in entries if getattr(e, "replicate", None) is not None]
    if not placed:
        return []
    split = "/".join(sorted({getattr(e, "split", "") or "?" for e in placed}))
    out = []
    for run in runs:
        mine = [e for e in placed if e.run == run]
        if not mine:
            continue
        for speed in [*_speed_groups(mine), ALL]:
            group = [e for e in mine if speed == ALL or e.speed == speed]
            reps = sorted({e.replicate for e in group})
            pos, rot = [], []
            for k in reps:
                errs = [e.errors for e in group if e.replicate == k]
                pos.append(_mean([x.position_rmse_cm for x in errs]))
                rot.append(_mean([x.rotation_rmse_deg for x in errs]))
            out.append(SeedSpread(run, speed, split, tuple(reps), tuple(pos), tuple(rot)))
    return out


def _spread_table(spreads: list[SeedSpread], labels: dict[str, str]) -> list[str]:
    lines = _md_header(["run", "speed", "seeds", "e_p (cm): mean ± sd [min, max]",
                        "e_r (deg): mean ± sd [min, max]"], [":--", ":--", "--:", "--:", "--:"])
    for sp in spreads:
        lines.append(_md_row([labels[sp.run], sp.speed or "?", str(len(sp.replicates)),
                              sp.text(sp.position), sp.text(sp.rotation)]))
    return lines


def _sequences(entries: Sequence[ErrorEntry]) -> list[tuple[str, str, str]]:
    """(sequence, object, speed) in first-seen order."""
    seen: dict[str, tuple[str, str, str]] = {}
    for e in entries:
        seen.setdefault(e.sequence, (e.sequence, e.object_name, e.speed))
    return list(seen.values())


def _md_row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _md_header(names: list[str], align: list[str]) -> list[str]:
    return [_md_row(names), "|" + "|".join(align) + "|"]


def _object_labels(seqs: list[tuple[str, str, str]]) -> dict[str, str]:
    """Object name per sequence; with the sequence name when object and speed repeat."""
    count: dict[tuple[str, str], int] = {}
    for _, obj, speed in seqs:
        count[(obj, speed)] = count.get((obj, speed), 0) + 1
    return {name: obj if count[(obj, speed)] == 1 else f"{obj} ({name})"
            for name, obj, speed in seqs}


def _table_one(entries, runs, labels, avgs) -> list[str]:
    seqs = _sequences(entries)
    objects = _object_labels(seqs)
    by_key = {(e.sequence, e.run): e.errors for e in entries}
    head = ["object", "speed"]
    for run in runs:
        head += [f"{labels[run]} e_p (cm)", f"{labels[run]} e_r (deg)"]
    lines = _md_header(head, [":--", ":--"] + ["--:"] * (2 * len(runs)))
    for name, _, speed in seqs:
        cells = [objects[name], speed or "?"]
        for run in runs:
            err = by_key.get((name, run))
            if err is None:
                cells += ["", ""]
            else:
                cells += [Cell(err.position_rmse_cm, err.position_std_cm).text(),
                          Cell(err.rotation_rmse_deg, err.rotation_std_deg).text()]
        lines.append(_md_row(cells))
    by_avg = {(a.run, a.speed): a for a in avgs}
    for speed in [*_speed_groups(entries), ALL]:
        cells = ["**average**", speed or "?"]
        for run in runs:
            a = by_avg.get((run, speed))
            cells += ["", ""] if a is None else [a.position.text(), a.rotation.text()]
        lines.append(_md_row(cells))
    return lines


def _tracked_table(entries, runs, labels) -> list[str]:
    by_key = {(e.sequence, e.run): e.errors for e in entries}
    lines = _md_header(["sequence", *[labels[r] for r in runs]], [":--"] + ["--:"] * len(runs))
    for name, _, _ in _sequences(entries):
        cells = [name]
        for run in runs:
            err = by_key.get((name, run))
            cells.append("" if err is None else f"{100 * err.tracked_fraction:.0f}%")
        lines.append(_md_row(cells))
    return lines


def _percent(value: float) -> str:
    return f"{value:.1f}" if math.isfinite(value) else "—"


_SCORE_HEADS = ("ADD", "ADD-S", "5cm/5°")
"""Column heads of the pose-accuracy cells: ADD AUC, ADD-S AUC (%), share within 5 cm and
5° (%)."""


def _pose_table(entries, runs, labels, avgs) -> list[str]:
    """Rows as Table I; per run ADD AUC, ADD-S AUC, 5 cm / 5° (%); then why any is missing."""
    seqs = _sequences(entries)
    objects = _object_labels(seqs)
    by_key = {(e.sequence, e.run): e for e in entries}
    head = ["object", "speed", "d (cm)"]
    for run in runs:
        head += [f"{labels[run]} {h}" for h in _SCORE_HEADS]
    lines = _md_header(head, [":--", ":--", "--:"] + ["--:"] * (3 * len(runs)))
    notes: dict[str, str] = {}
    for name, _, speed in seqs:
        mine = [by_key[(name, run)] for run in runs if (name, run) in by_key]
        diameters = [s.diameter_m for s in map(_scores, mine)
                     if s is not None and math.isfinite(s.diameter_m)]
        cells = [objects[name], speed or "?",
                 f"{100 * diameters[0]:.1f}" if diameters else "—"]
        for run in runs:
            e = by_key.get((name, run))
            cells += ["", "", ""] if e is None else [_percent(v) for v in _score_values(e)]
            scores = _scores(e) if e is not None else None
            if scores is not None and scores.note:
                notes.setdefault(name, scores.note)
        lines.append(_md_row(cells))
    by_avg = {(a.run, a.speed): a for a in avgs}
    for speed in [*_speed_groups(entries), ALL]:
        cells = ["**average**", speed or "?", ""]
        for run in runs:
            a = by_avg.get((run, speed))
            cells += ["", "", ""] if a is None else [
                _percent(a.add_auc), _percent(a.adds_auc), _percent(a.within_5cm_5deg)]
        lines.append(_md_row(cells))
    if notes:
        lines += [""] + [f"— {name}: not computed, {note}." for name, note in notes.items()]
    return lines


def _average_table(avgs, runs, labels, groups) -> list[str]:
    """Rows = runs; the RMSE cells per group, then the pose-accuracy cells per group."""
    by_avg = {(a.run, a.speed): a for a in avgs}
    head = ["run"]
    for g in groups:
        head += [f"{g} e_p (cm)", f"{g} e_r (deg)"]
    for g in groups:
        head += [f"{g} {h}" for h in _SCORE_HEADS]
    lines = _md_header(head, [":--"] + ["--:"] * (5 * len(groups)))
    for run in runs:
        cells = [labels[run]]
        for g in groups:
            a = by_avg.get((run, g))
            cells += ["", ""] if a is None else [a.position.text(), a.rotation.text()]
        for g in groups:
            a = by_avg.get((run, g))
            cells += ["", "", ""] if a is None else [
                _percent(a.add_auc), _percent(a.adds_auc), _percent(a.within_5cm_5deg)]
        lines.append(_md_row(cells))
    return lines


def markdown_tables(entries: Sequence[ErrorEntry], methods: Sequence[str],
                    labels: dict[str, str] | None = None, ablations: Sequence[str] = (),
                    caption: str = "") -> str:
    """Tables I, tracked samples, pose accuracy, II and (with ``ablations``) III as Markdown.

    Args:
        entries: one per (sequence, run).
        methods: the runs of Tables I and II, in column order.
        labels: run name -> display label (default: the name).
        ablations: the runs of Table III after ``full`` (empty: no Table III).
        caption: a line under the title (e.g. the pose source).
    """
    labels = {**{e.run: e.run for e in entries}, **(labels or {})}
    runs = list(dict.fromkeys([*methods, *(["full", *ablations] if ablations else [])]))
    avgs = average_rows(entries, runs)
    groups = [*_speed_groups(entries), ALL]
    n = len(_sequences(entries))
    out = ["# evtrack benchmark", ""]
    if caption:
        out += [f"Pose source: {caption}", ""]
    out += [f"Sequences: {n}. Cells: RMSE ± σ over the tracked samples of each sequence, "
            "position e_p in cm (Euclidean), rotation e_r in deg (geodesic); averages are "
            "means of the per-sequence values.", ""]
    out += ["## Table I: tracking error per sequence", ""]
    out += _table_one(entries, list(methods), labels, avgs) + [""]
    out += ["## Tracked samples (share of each trajectory in the RMSE)", ""]
    out += _tracked_table(entries, list(methods), labels) + [""]
    out += ["## Pose accuracy per sequence: ADD / ADD-S AUC (%, up to 10 % of the diameter) "
            "and 5 cm / 5° (%)", ""]
    out += ["Over every ground-truth sample of each sequence, scored with the tracker's "
            "latest output; those without an estimate (before the first pose, lost) fail. "
            "ADD: mean distance of the mesh's points under the "
            "estimated and the true pose; ADD-S: from each true point to the nearest "
            "estimated one, the fair score for symmetric objects. AUC: area under the "
            "accuracy over thresholds 0 to 0.1 d (d: the object's diameter). 5cm/5°: share "
            "within 5 cm and 5° at once. Higher is better.", ""]
    out += _pose_table(entries, list(methods), labels, avgs) + [""]
    out += ["## Table II: average tracking error", ""]
    out += _average_table(avgs, list(methods), labels, groups) + [""]
    if ablations:
        out += ["## Table III: ablation of the full method", ""]
        out += _average_table(avgs, ["full", *ablations], labels, groups) + [""]
    spreads = seed_spreads(entries, runs)
    if spreads:
        out += [f"## Spread over seeds ({spreads[0].split} split)", ""]
        out += ["Each seed replicate's average (mean of its sequences' RMSEs), then the mean, "
                "sample standard deviation and range of those averages over the replicates.",
                ""]
        out += _spread_table(spreads, labels) + [""]
    return "\n".join(out)


def _num(value: float) -> str:
    return repr(float(value)) if math.isfinite(value) else "nan"


def csv_table(entries: Sequence[ErrorEntry], runs: Sequence[str],
              labels: dict[str, str] | None = None) -> str:
    """Long-format CSV: one row per (sequence, run), then one per (run, speed group) average.

    Columns: :data:`CSV_COLUMNS`; ``table`` is ``sequence`` or ``average``. The pose
    accuracy (``add_auc_pct``, ``adds_auc_pct``, ``within_5cm_5deg_pct``) is NaN where not
    measured.
    """
    labels = {**{e.run: e.run for e in entries}, **(labels or {})}
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    order = {r: i for i, r in enumerate(runs)}
    for e in sorted((e for e in entries if e.run in order), key=lambda e: order[e.run]):
        x, scores = e.errors, _scores(e)
        diameter_cm = 100 * scores.diameter_m if scores is not None else math.nan
        writer.writerow(["sequence", e.sequence, e.object_name, e.speed, e.run, labels[e.run],
                         _num(x.position_rmse_cm), _num(x.position_std_cm),
                         _num(x.rotation_rmse_deg), _num(x.rotation_std_deg), x.samples,
                         x.total, _num(x.tracked_fraction), 1,
                         *(_num(v) for v in _score_values(e)), _num(diameter_cm)])
    for a in average_rows(entries, list(runs)):
        frac = a.samples / a.total if a.total else math.nan
        writer.writerow(["average", "", ALL, a.speed, a.run, labels[a.run],
                         _num(a.position.rmse), _num(a.position.std), _num(a.rotation.rmse),
                         _num(a.rotation.std), a.samples, a.total, _num(frac), a.sequences,
                         _num(a.add_auc), _num(a.adds_auc), _num(a.within_5cm_5deg), "nan"])
    return buf.getvalue()


def write_tables(entries: Sequence[ErrorEntry], out_dir: str | Path, methods: Sequence[str],
                 labels: dict[str, str] | None = None, ablations: Sequence[str] = (),
                 caption: str = "") -> str:
    """Write ``results.md`` and ``results.csv`` to ``out_dir`` atomically; return the Markdown."""
    from evtrack.utils import atomic_write_text

    out_dir = Path(out_dir)
    text = markdown_tables(entries, methods, labels, ablations, caption)
    runs = list(dict.fromkeys([*methods, *(["full", *ablations] if ablations else [])]))
    atomic_write_text(out_dir / "results.md", text)
    atomic_write_text(out_dir / "results.csv", csv_table(entries, runs, labels))
    return text
