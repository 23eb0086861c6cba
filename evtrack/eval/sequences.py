"""Find the sequences of a benchmark folder and label them by object and speed.

A benchmark folder is a sequence folder itself (it holds ``meta.yaml``) or any folder whose
subfolders (at any depth) are sequence folders, such as the output of
``evtrack simulate-benchmark``. A sequence folder is not searched further.

Labels:
    object: ``meta.yaml``'s ``object.name`` (e.g. ``"003_cracker_box"``).
    speed: the simulator's trajectory preset (``meta.yaml`` ``extra.config.trajectory.preset``),
        else the folder name's last ``_``-separated part when it is a known preset
        (``box_faster`` -> ``faster``), else ``""`` (unknown).
    split, replicate: the sequence's place in the held-out protocol (``meta.yaml``
        ``extra.benchmark``, written by ``evtrack simulate-benchmark``; see
        :mod:`evtrack.sim.benchmark_set`): ``"tuning"`` or ``"test"`` and the seed's index
        within its object and preset; ``""`` and ``None`` for other sequences.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from evtrack.errors import EvtrackError
from evtrack.sequence import GT_FILE, META_FILE, Sequence

__all__ = ["SPEEDS", "BenchmarkSequence", "find_sequences", "speed_label", "split_label",
           "require_ground_truth", "require_one_split"]

#: The benchmark's speed presets, in table order.
SPEEDS = ("regular", "faster")


@dataclass(frozen=True)
class BenchmarkSequence:
    """One sequence of a benchmark.

    Attributes:
        path: the sequence folder.
        name: its path relative to the benchmark folder (``/``-separated), or its folder name
            when the benchmark folder is the sequence itself.
        object_name: the tracked object (``meta.yaml`` ``object.name``).
        speed: ``"regular"``, ``"faster"``, another preset name, or ``""`` when unknown.
        split: ``"tuning"``, ``"test"``, or ``""`` outside the held-out protocol.
        replicate: the seed's index within its object and preset in the split, or ``None``.
        objects: the names of all its objects when it has several (``meta.yaml``
            ``objects``), else empty.
    """

    path: Path
    name: str
    object_name: str
    speed: str
    split: str = ""
    replicate: int | None = None
    objects: tuple[str, ...] = ()

    @property
    def file_stem(self) -> str:
        """``name`` made safe as a file name (``/`` -> ``__``)."""
        return self.name.replace("/", "__")

    def load(self) -> Sequence:
        return Sequence.load(self.path)


def speed_label(sequence: Sequence) -> str:
    """The speed preset of a sequence (see the module docstring), ``""`` if unknown.

    An imported recording has no preset: it is grouped by its dataset (``meta.extra.dataset``,
    e.g. ``"YCB-Ev"``), or as ``"recording"``.
    """
    extra = sequence.meta.extra if isinstance(sequence.meta.extra, dict) else {}
    config = extra.get("config")
    trajectory = config.get("trajectory") if isinstance(config, dict) else None
    preset = trajectory.get("preset") if isinstance(trajectory, dict) else None
    if isinstance(preset, str) and preset:
        return preset
    folder = sequence.root.name if sequence.root is not None else sequence.meta.name
    tail = folder.rsplit("_", 1)[-1] if "_" in folder else ""
    if tail in SPEEDS:
        return tail
    if sequence.meta.source == "recording":
        dataset = extra.get("dataset")
        return dataset if isinstance(dataset, str) and dataset else "recording"
    return ""


def split_label(sequence: Sequence) -> tuple[str, int | None]:
    """``(split, replicate)`` from ``meta.yaml`` ``extra.benchmark``; ``("", None)`` when the
    sequence is not part of a split."""
    extra = sequence.meta.extra if isinstance(sequence.meta.extra, dict) else {}
    info = extra.get("benchmark")
    if not isinstance(info, dict):
        return "", None
    split = info.get("split")
    replicate = info.get("replicate")
    return (split if isinstance(split, str) else "",
            replicate if isinstance(replicate, int) and not isinstance(replicate, bool)
            else None)


def _sequence_folders(root: Path) -> list[Path]:
    if (root / META_FILE).is_file():
        return [root]
    found: list[Path] = []
    for child in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        found += _sequence_folders(child)
    return found


def _sort_key(s: BenchmarkSequence) -> tuple:
    rank = SPEEDS.index(s.speed) if s.speed in SPEEDS else len(SPEEDS)
    return (s.object_name, rank, s.speed, s.name)


def find_sequences(root: str | Path) -> list[BenchmarkSequence]:
    """The sequences under ``root``, sorted by object, then speed (regular, faster, others).

    Raises:
        EvtrackError: ``root`` is missing, is not a folder, or holds no sequence folder.
        EventFileError, ConfigError: a sequence folder that cannot be opened (naming it).
    """
    root = Path(root)
    if not root.exists():
        raise EvtrackError(f"{root}: benchmark folder not found")
    if not root.is_dir():
        raise EvtrackError(f"{root}: not a folder (give a sequence folder or a folder of "
                           "sequence folders)")
    folders = _sequence_folders(root)
    if not folders:
        raise EvtrackError(f"{root}: no sequence folders found (folders holding {META_FILE}); "
                           "make some with 'evtrack simulate-benchmark --out DIR'")
    out = []
    for folder in folders:
        seq = Sequence.load(folder)
        name = folder.name if folder == root else folder.relative_to(root).as_posix()
        out.append(BenchmarkSequence(folder, name, seq.meta.object_name or "?",
                                     speed_label(seq), *split_label(seq),
                                     objects=tuple(o.name for o in seq.meta.objects)))
    return sorted(out, key=_sort_key)


def require_one_split(sequences: list[BenchmarkSequence]) -> None:
    """Raise when the sequences mix the tuning and the test split: an average over both would
    report results partly on the sequences the settings were chosen on."""
    splits = sorted({s.split for s in sequences if s.split})
    if len(splits) > 1:
        examples = {sp: next(str(s.path) for s in sequences if s.split == sp) for sp in splits}
        raise EvtrackError(
            "the benchmark folder mixes the splits " + ", ".join(
                f"{sp!r} (e.g. {path})" for sp, path in examples.items())
            + "; evaluate each split's folder on its own (tuning: where settings are chosen, "
              "test: what is reported)")


def require_ground_truth(sequences: list[BenchmarkSequence]) -> None:
    """Raise naming every sequence folder without ground truth (``groundtruth.h5``)."""
    missing = [str(s.path) for s in sequences if not (s.path / GT_FILE).is_file()]
    if missing:
        raise EvtrackError(
            "no ground truth (groundtruth.h5) in: " + ", ".join(missing)
            + "; evaluation needs ground-truth poses (use 'evtrack track' for sequences "
              "without them)")
