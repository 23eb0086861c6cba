"""RoI depth (evtrack.tracking.roi_depth): one lookup per depth map for a step group gives
what the per-step lookup gives."""

from __future__ import annotations

import numpy as np
import torch
from tracker_helpers import make_tracker, stream

from evtrack.tracking.roi_depth import RoiDepth


def test_group_depth_lookup_equals_step_by_step(fast_sequence, monkeypatch):
    """The sensor depth of a step group's RoIs is looked up once per depth map
    (RoiDepth.step); with frames dropped (depth maps that expire and arrive inside a
    group) it must give what the per-step lookup gives: the same trajectory, bit for bit, and
    the same fallbacks."""
    seq = fast_sequence
    times = seq.rgb_times_us.numpy()
    dropped = ((times >= 150_000) & (times < 400_000)) | (
        np.random.default_rng(1).random(len(times)) < 0.5)

    def run():
        tracker, _ = make_tracker(seq, method="full")
        return stream(tracker, seq, keep_frame=lambda i: not dropped[i]), tracker.stats

    grouped, st_grouped = run()
    calls = []

    def per_step(self, flows, k, poly, pose, t_now):
        calls.append(k)
        return self.lookup(flows.step(k)[0], poly, pose, t_now)

    monkeypatch.setattr(RoiDepth, "step", per_step)
    stepped, st_stepped = run()
    assert calls  # the patched lookup was used
    assert st_grouped.depth_fallbacks == st_stepped.depth_fallbacks > 0
    assert st_grouped.roi_flows == st_stepped.roi_flows
    assert torch.equal(grouped.poses.nan_to_num(7.0), stepped.poses.nan_to_num(7.0))
