"""The work per step through the tracker (``TrackerConfig.load``): the event cap, the sampled
search and the search budget bound the flow's work whatever the chunking of the events, and
keep the error bounded."""

from __future__ import annotations

import numpy as np
import torch
from robustness_scenes import merged, noise_burst
from tracker_helpers import make_tracker, record_flow_calls

from evtrack.camera import PinholeCamera
from evtrack.eval.metrics import tracking_errors
from evtrack.events import Events
from evtrack.flow.scenes import translating_texture
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.tracker import Tracker

CAM = PinholeCamera(100.0, 100.0, 63.5, 47.5, 128, 96)
BIG_CUBE = np.array([[x, y, z] for x in (-.15, .15) for y in (-.15, .15) for z in (-.05, .05)])


def _textured_object_with_burst(seed: int = 0) -> Events:
    """A texture moving at 300 px/s seen only inside the big cube's silhouette at 0.6 m
    (x 36..91, y 20..75 px) for 50 ms, and a 500 Hz-per-pixel burst over the sensor in
    [20, 30) ms."""

    ev, _ = translating_texture((128, 96), velocity=(300.0, 0.0), duration_us=50_000,
                                seed=seed)
    inside = (ev.x >= 40) & (ev.x < 88) & (ev.y >= 24) & (ev.y < 72)
    burst = noise_burst((128, 96), 20_000, 10_000, 500 * 128 * 96, seed=seed + 1)
    return merged(ev[inside], burst)


def test_event_cap_bounds_the_work_per_step_whatever_the_chunking() -> None:
    """At most ``load.max_events_per_step`` events of a step reach the flow (the rest are thinned
    and counted), the burst steps are found, and both decisions do not depend on how the
    events are chunked: one chunk and random chunks give the same output bit for bit."""
    ev = _textured_object_with_burst()
    cap = 200  # about a quarter of the object's events
    config = TrackerConfig.from_dict({"flow": {"roi_size": 16},
                                      "load": {"max_events_per_step": cap},
                                      "mask_margin_px": 4.0})
    outputs = []
    for chunks in ("one", "random"):
        tracker, calls = _track_textured_object(config, ev, chunks, seed=3)
        st = tracker.stats
        assert st.burst_steps == 10
        assert st.events_thinned > 0
        per_group = cap * config.flow_batch_steps
        assert max(c[0] for c in calls) <= per_group
        assert sum(c[0] for c in calls) == (st.events_on_object - st.events_in_bursts
                                            - st.events_thinned)
        assert st.roi_flows > 0 and np.isfinite(tracker.twist()).all()
        outputs.append((tracker.trajectory(), st.to_dict()))
    (a, sa), (b, sb) = outputs
    assert torch.equal(a.poses, b.poses) and torch.equal(a.twists, b.twists)
    sa.pop("time_s"), sb.pop("time_s")
    assert sa == sb


def _track_textured_object(config: TrackerConfig, ev: Events, chunks: str, seed: int):
    """Track ``ev`` from the big cube's pose at 0.6 m, pushed in one chunk or in 41 random
    ones; returns the tracker and its recorded flow calls (:func:`record_flow_calls`)."""
    tracker = Tracker(config, camera=CAM, mesh=BIG_CUBE)
    start = np.eye(4)
    start[2, 3] = 0.6
    tracker.reset(start, t_us=0)
    calls = record_flow_calls(tracker)
    if chunks == "one":
        tracker.push_events(ev)
    else:
        rng = np.random.default_rng(seed)
        cuts = np.sort(rng.choice(len(ev), 40, replace=False))
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(ev)], strict=True):
            tracker.push_events(ev[int(a):int(b)])
    tracker.flush()
    return tracker, calls


def test_sampled_search_is_counted_and_independent_of_the_chunking() -> None:
    """With ``load.search_per_roi_window`` the flow searches a sample of each dense RoI window:
    the events given to the flow but not searched are counted, the sample (a hash of the
    stream index, counted per step group) does not depend on how the events were pushed,
    and it changes the RoI flows only where a window's sample is short of the data term."""
    ev = _textured_object_with_burst()
    base = {"flow": {"roi_size": 16}, "load": {"max_events_per_step": 0}, "mask_margin_px": 4.0}
    sampled = TrackerConfig.from_dict({**base, "load": {**base["load"],
                                                         "search_per_roi_window": 6}})
    runs_ = [_track_textured_object(sampled, ev, chunks, seed=5) for chunks in ("one", "random")]
    (a, calls_a), (b, calls_b) = runs_
    searched_a, searched_b = (sum(c[3] for c in calls) for calls in (calls_a, calls_b))
    st = a.stats
    given = st.events_on_object - st.events_in_bursts
    assert 0 < st.events_unsearched < given
    assert searched_a == searched_b == given - st.events_unsearched
    assert torch.equal(a.trajectory().poses, b.trajectory().poses)
    sa, sb = a.stats.to_dict(), b.stats.to_dict()
    sa.pop("time_s"), sb.pop("time_s")
    assert sa == sb
    whole, calls_whole = _track_textured_object(
        TrackerConfig.from_dict({**base, "load": {**base["load"], "search_per_roi_window": 0}}),
        ev, "one", seed=5)
    assert whole.stats.events_unsearched == 0 and sum(c[3] for c in calls_whole) == given
    assert whole.stats.roi_flows > 0 and st.roi_flows > 0
    assert not torch.equal(whole.trajectory().twists, a.trajectory().twists)


def test_sampled_search_keeps_the_error_bounded(fast_sequence, runs) -> None:
    """A sample of 4 events per RoI window (an eighth of the tracker's default) still
    tracks the fast sequence close to the whole search: measured 5.25 cm / 12.27 deg with
    81 % of the flow's events unsearched, against 4.27 / 12.37 (2026-11-27). Bounds: whole
    + 2 cm and + 3 deg."""
    whole, _ = make_tracker(fast_sequence, method="full", load={"search_per_roi_window": 0})
    sampled, _ = make_tracker(fast_sequence, method="full", load={"search_per_roi_window": 4})
    gt = fast_sequence.ground_truth
    ref = tracking_errors(whole.track(fast_sequence), gt)
    err = tracking_errors(sampled.track(fast_sequence), gt)
    share = sampled.stats.events_unsearched / sampled.stats.events_on_object
    print(f"sampled {err.position_rmse_cm:.2f} cm / {err.rotation_rmse_deg:.2f} deg, whole "
          f"{ref.position_rmse_cm:.2f} / {ref.rotation_rmse_deg:.2f}, {share:.0%} unsearched")
    assert whole.stats.events_unsearched == 0 and share > 0.2
    assert err.position_rmse_cm < ref.position_rmse_cm + 2.0
    assert err.rotation_rmse_deg < ref.rotation_rmse_deg + 3.0


def test_search_budget_bounds_the_searched_events_whatever_the_chunking() -> None:
    """With ``load.max_searched_per_step`` the flow searches at most that many events per step
    (over a step group, by whole cells), every event still reaches it (none is thinned), the
    rest are counted as unsearched, and the choice does not depend on how the events were
    pushed."""
    ev = _textured_object_with_burst()
    budget = 40
    config = TrackerConfig.from_dict({"flow": {"roi_size": 16}, "mask_margin_px": 4.0,
                                      "load": {"max_events_per_step": 0,
                                               "search_per_roi_window": 0,
                                               "max_searched_per_step": budget}})
    (a, calls_a), (b, calls_b) = (_track_textured_object(config, ev, chunks, seed=7)
                                  for chunks in ("one", "random"))
    st = a.stats
    given = st.events_on_object - st.events_in_bursts
    assert st.events_thinned == 0 and sum(c[0] for c in calls_a) == given
    assert max(c[3] for c in calls_a) <= budget * config.flow_batch_steps
    assert max(c[0] for c in calls_a) > budget * config.flow_batch_steps  # it did cut
    assert sum(c[3] for c in calls_a) == given - st.events_unsearched > 0
    assert [c[3] for c in calls_a] == [c[3] for c in calls_b]
    assert torch.equal(a.trajectory().poses, b.trajectory().poses)
    sa, sb = a.stats.to_dict(), b.stats.to_dict()
    sa.pop("time_s"), sb.pop("time_s")
    assert sa == sb
    assert st.roi_flows > 0 and np.isfinite(a.twist()).all()


def test_search_budget_keeps_the_error_bounded(fast_sequence, runs) -> None:
    """A search budget of half the fast sequence's events per step (on this small sensor a
    few RoIs hold most of them) still tracks it close to the whole search: measured 5.66 cm /
    13.37 deg with 62 % of the flow's events unsearched and 39 % of the RoI flows, against
    4.27 / 12.37 (2026-11-27; with cells of 2 x 2 RoIs 5.81 / 14.67). Bounds: whole + 2.5 cm
    and + 4 deg."""
    whole, _ = make_tracker(fast_sequence, method="full", load={"search_per_roi_window": 0,
                                                                "max_searched_per_step": 0})
    gt = fast_sequence.ground_truth
    ref = tracking_errors(whole.track(fast_sequence), gt)
    budget = max(1, int(whole.stats.events_on_object / whole.stats.steps / 2))
    cut, _ = make_tracker(fast_sequence, method="full", load={"search_per_roi_window": 0,
                                                              "max_searched_per_step": budget})
    calls = record_flow_calls(cut)
    err = tracking_errors(cut.track(fast_sequence), gt)
    given = sum(c[0] for c in calls)
    print(f"budget {budget} per step: {err.position_rmse_cm:.2f} cm / "
          f"{err.rotation_rmse_deg:.2f} deg, whole {ref.position_rmse_cm:.2f} / "
          f"{ref.rotation_rmse_deg:.2f}, {cut.stats.events_unsearched / given:.0%} unsearched, "
          f"RoI flows {cut.stats.roi_flows} / {whole.stats.roi_flows}")
    assert whole.stats.events_unsearched == 0
    assert sum(c[0] - c[3] for c in calls) == cut.stats.events_unsearched > 0.3 * given
    assert max(c[3] for c in calls) <= budget * cut.config.flow_batch_steps
    assert cut.stats.events_thinned == whole.stats.events_thinned
    assert err.position_rmse_cm < ref.position_rmse_cm + 2.5
    assert err.rotation_rmse_deg < ref.rotation_rmse_deg + 4.0


def test_thinned_tracking_keeps_the_error_bounded(fast_sequence, runs) -> None:
    """A budget of 60 events per step, about half the fast sequence's mean rate: the track
    stays within a bound of the clean run's. Measured: 10.37 cm / 14.11 deg with 49 % of the
    events thinned, against 5.50 / 14.02 clean; thinning single events (the former rule) gave
    8.72 / 14.80 with 41 % thinned on this sparse scene, but 34.5 cm / 58 deg on the dense
    cracker box `faster` with a budget of 4000 events per step (9.24 / 13.8 by cells, 4.35 /
    6.5 unthinned; see the next test for why). Bounds: clean + 6 cm and + 3 deg."""
    tracker, _ = make_tracker(fast_sequence, method="full", load={"max_events_per_step": 60})
    traj = tracker.track(fast_sequence)
    clean, _, _ = runs.get("full")
    st = tracker.stats
    assert 0.2 * st.events < st.events_thinned < 0.8 * st.events
    gt = fast_sequence.ground_truth
    err, ref = tracking_errors(traj, gt), tracking_errors(clean, gt)
    print(f"thinned {err.position_rmse_cm:.2f} cm / {err.rotation_rmse_deg:.2f} deg, clean "
          f"{ref.position_rmse_cm:.2f} / {ref.rotation_rmse_deg:.2f}, "
          f"{st.events_thinned / st.events:.0%} of the events thinned")
    assert err.position_rmse_cm < ref.position_rmse_cm + 6.0
    assert err.rotation_rmse_deg < ref.rotation_rmse_deg + 3.0
