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
