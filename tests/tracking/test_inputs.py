"""The clock and input queues (evtrack.tracking.inputs): measurements in availability order
(arrival order at equal times), frames in time order, the clock's start and its event checks."""

from __future__ import annotations

from concurrent.futures import Future

import numpy as np
import pytest
import torch

from evtrack.errors import EventsError
from evtrack.tracking.inputs import (
    DepthFrame,
    FrameQueue,
    MeasurementQueue,
    PendingPoseCall,
    PoseMiss,
    StreamClock,
    TwistMeasurement,
)
from evtrack.tracking.pose_sources import PoseMeasurement


def _drain(queue: MeasurementQueue, t_now: int) -> list:
    out = []
    while (due := queue.pop_due(t_now)) is not None:
        out.append(due)
    return out


def test_measurements_come_out_by_availability_then_arrival() -> None:
    queue = MeasurementQueue()
    rng = np.random.default_rng(0)
    pushed = []
    for i in range(200):
        available = int(rng.integers(0, 20)) * 1000
        item = PoseMiss(i)
        queue.push(available, item)
        pushed.append((available, i, item))
    assert queue.next_due_us == min(a for a, _, _ in pushed)
    expected = [(a, item) for a, _, item in sorted(pushed, key=lambda p: (p[0], p[1]))]
    due_by_10ms = [p for p in expected if p[0] <= 10_000]
    assert _drain(queue, 10_000) == due_by_10ms  # nothing later than t_now
    assert _drain(queue, 10**9) == expected[len(due_by_10ms):]
    assert queue.next_due_us is None and len(queue) == 0


def test_every_measurement_type_queues() -> None:
    queue = MeasurementQueue()
    items = [PoseMeasurement(5, torch.eye(4, dtype=torch.float64)), PoseMiss(5),
             DepthFrame(5, np.zeros((2, 2))), PendingPoseCall(5, Future()),
             TwistMeasurement(5, torch.zeros(1, 6), torch.eye(6)[None])]
    for item in items:
        queue.push(7, item)
    assert [item for _, item in _drain(queue, 7)] == items


def test_pending_calls_are_replaced_in_their_arrival_order() -> None:
    """Settled worker calls take their new availability and keep their place among equals."""
    queue = MeasurementQueue()
    calls = [PendingPoseCall(t, Future()) for t in (10, 20, 30)]
    queue.push(100, calls[0])
    queue.push(50, PoseMiss(1))
    queue.push(100, calls[1])
    queue.push(100, PoseMiss(2))
    queue.push(300, calls[2])
    queue.replace_pending_calls(
        lambda available, call: (available if call.t_us != 30 else 60, PoseMiss(call.t_us)))
    got = [(a, item.t_us) for a, item in _drain(queue, 10**9)]
    assert got == [(50, 1), (60, 30), (100, 10), (100, 20), (100, 2)]


def test_frames_come_out_in_time_order_before_a_time() -> None:
    frames = FrameQueue()
    for t in (30, 10, 20, 10):
        frames.push(t, f"rgb{t}", None)
    assert frames.next_us == 10
    taken = []
    for t_us, rgb, _ in frames.pop_before(21):
        taken.append((t_us, rgb))
        if t_us == 20:
            frames.push(15, "late", None)  # pushed while one is processed: taken in its turn
    assert taken == [(10, "rgb10"), (10, "rgb10"), (20, "rgb20"), (15, "late")]
    assert frames.next_us == 30 and len(frames) == 1


def test_the_clock_starts_on_a_step_and_checks_event_order() -> None:
    clock = StreamClock(1000)
    clock.check_events(5, 9)  # nothing pushed yet: anything goes
    assert clock.start(12_345) == 12_000 and clock.now == 12_000
    clock.last_event_us = 12_500
    clock.moved_by = "push_frame(t_us=12000)"
    with pytest.raises(EventsError, match="before the last event pushed"):
        clock.check_events(12_400, 12_600)
    clock.last_event_us = None
    with pytest.raises(EventsError, match=r"before the tracker's clock \(12000 µs, moved there "
                                          r"by push_frame\(t_us=12000\)\)"):
        clock.check_events(11_999, 12_600)
    clock.check_events(12_000, 12_600)
