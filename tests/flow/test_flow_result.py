"""FlowResult's summary line (what printing a result shows instead of every tensor)."""

from __future__ import annotations

from evtrack.flow import TripletFlow
from evtrack.flow.result import FlowResult
from evtrack.flow.scenes import translating_texture


def test_repr_summarises_instead_of_dumping_the_tensors() -> None:
    ev, _ = translating_texture((128, 96), velocity=(300.0, 0.0), duration_us=30_000)
    res = TripletFlow(roi_size=16, window_us=2000)(ev)
    text = repr(res)
    assert text.startswith(f"FlowResult({len(res)} RoI flows, t ")
    speed = int(text.split("median speed ")[1].split(" px/s")[0])
    assert abs(speed - 300) <= 30  # the texture moves at 300 px/s
    assert "tensor(" not in text and len(text) < 200
    assert repr(FlowResult.empty()) == "FlowResult(0 RoI flows, device=cpu)"
