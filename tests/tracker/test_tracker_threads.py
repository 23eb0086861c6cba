"""Tracker.track sets torch's thread count from its config, within the free cores, and puts
the caller's count back."""

from __future__ import annotations

import pytest
import torch
from tracker_helpers import make_tracker

from evtrack import utils


@pytest.mark.parametrize(("configured", "cores", "expected"), [
    (2, 4, 2), (2, 1, 1), (3, 2, 2), (0, 2, None),  # None: the caller's count is left alone
])
def test_track_runs_on_the_configured_threads(static_sequence, monkeypatch, configured, cores,
                                              expected) -> None:
    tracker, _ = make_tracker(static_sequence, method="pose", torch_threads=configured)
    seen: list[int] = []
    monkeypatch.setattr(tracker, "_track",
                        lambda seq, progress: seen.append(torch.get_num_threads()))
    monkeypatch.setattr(utils, "usable_cpu_count", lambda: cores)
    before = torch.get_num_threads()
    # a caller's count that differs from every expected value, so a leak would show
    torch.set_num_threads(5)
    try:
        tracker.track(static_sequence)
        assert seen == [5 if expected is None else expected]
        assert torch.get_num_threads() == 5
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("streaming", [False, True])
def test_blas_runs_on_the_configured_threads_while_tracking(static_sequence, streaming) -> None:
    """numpy's BLAS is limited to ``blas_threads`` while the tracker works (offline and in the
    streaming calls) and the caller's setting is back afterwards."""
    threadpoolctl = pytest.importorskip("threadpoolctl")

    def blas() -> set[int]:
        return {p["num_threads"] for p in threadpoolctl.threadpool_info()
                if p["user_api"] == "blas"}

    if not blas():
        pytest.skip("threadpoolctl finds no BLAS library in this process")
    tracker, source = make_tracker(static_sequence, method="pose", blas_threads=1)
    seen: list[set[int]] = []
    inner = source.__call__

    class Recording:
        uses_depth = False

        def __call__(self, *args):
            seen.append(blas())
            return inner(*args)

    tracker.pose_source = Recording()
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        if blas() != {2}:
            pytest.skip("this BLAS cannot run 2 threads")
        if streaming:  # the object at rest: frames only
            times = static_sequence.rgb_times_us.tolist()
            for i, t in enumerate(times):
                tracker.push_frame(t, rgb=lambda i=i: static_sequence.rgb(i))
            tracker.advance(times[-1] + 1)
            tracker.flush()
        else:
            tracker.track(static_sequence)
        assert blas() == {2}
    assert seen and all(s == {1} for s in seen)
