"""The speed group of a benchmark sequence: its preset, its folder name, or its dataset."""

from __future__ import annotations

import pytest

from evtrack.camera import PinholeCamera
from evtrack.eval.sequences import speed_label
from evtrack.sequence import Sequence, SequenceMeta

CAM = PinholeCamera(100, 100, 20, 15, 40, 30)


@pytest.mark.parametrize("meta, label", [
    (SequenceMeta(CAM, name="x", source="simulation",
                  extra={"config": {"trajectory": {"preset": "faster"}}}), "faster"),
    (SequenceMeta(CAM, name="box_regular", source="simulation"), "regular"),
    (SequenceMeta(CAM, name="box", source="simulation"), ""),
    (SequenceMeta(CAM, name="ycbev_01_x", source="recording", extra={"dataset": "YCB-Ev"}),
     "YCB-Ev"),
    (SequenceMeta(CAM, name="mine", source="recording"), "recording"),
])
def test_speed_label(meta: SequenceMeta, label: str) -> None:
    assert speed_label(Sequence(meta)) == label


@pytest.mark.parametrize("extra, label", [
    ({"benchmark": {"split": "test", "replicate": 2, "seed": 5212, "seeds": 3}}, ("test", 2)),
    ({"benchmark": {"split": "tuning", "replicate": 0}}, ("tuning", 0)),
    ({"benchmark": {"split": "test", "replicate": True}}, ("test", None)),
    ({"benchmark": "test"}, ("", None)),
    ({}, ("", None)),
])
def test_split_label(extra: dict, label: tuple) -> None:
    from evtrack.eval.sequences import split_label

    meta = SequenceMeta(CAM, name="x", source="simulation", extra=extra)
    assert split_label(Sequence(meta)) == label


def test_a_folder_mixing_the_splits_is_refused(tmp_path) -> None:
    from pathlib import Path

    from evtrack.errors import EvtrackError
    from evtrack.eval.sequences import BenchmarkSequence, require_one_split

    seqs = [BenchmarkSequence(Path(f"/b/{n}"), n, "o", "faster", split, 0)
            for n, split in (("a", "tuning"), ("b", "test"), ("c", ""))]
    with pytest.raises(EvtrackError, match=r"mixes the splits 'test' \(e\.g\. /b/b\), "
                                           r"'tuning' \(e\.g\. /b/a\)"):
        require_one_split(seqs)
    require_one_split(seqs[1:])  # one split and a sequence outside any: fine
