"""Robustness of the tracker (issue 7, deliverable 5): each case a test with a stated bound.

Sequences are simulated at 128x96 (tests/tracker/conftest.py, robustness_scenes.py) and tracked
with the ``full`` method, the test settings of tracker_helpers.py (poses at 10 Hz arriving
100 ms late) and the noisy oracle pose source (1 cm and 0.03 rad per axis). Every bound was set
from a measured clean baseline with a margin; the docstrings give the values measured when the
test was written. Input checks of the streaming API that test_tracker_inputs.py already covers
(unsorted, out-of-sensor, wrong-size events and depth frames, frames without depth) are not
repeated here.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from robustness_scenes import (
    VisibleOnlySource,
    knot_trajectory,
    merged,
    noise_burst,
    simulate_sequence,
    with_events,
)
from tracker_helpers import ORACLE_NOISE, TEST_TRACKER, make_tracker, record_flow_calls, stream

from evtrack.camera import PinholeCamera
from evtrack.errors import EventsError
from evtrack.eval.metrics import tracking_errors
from evtrack.events import Events
from evtrack.flow.scenes import translating_texture
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.pose_sources import NetworkPoseSource, OraclePoseSource, PoseMeasurement
from evtrack.tracking.silhouette import Silhouette
from evtrack.tracking.tracker import Tracker
from evtrack.tracking.trajectory import STATUS_LOST, STATUS_TRACKING

LATENCY_US = int(TEST_TRACKER["pose_latency_ms"] * 1000)
PERIOD_US = int(round(1e6 / TEST_TRACKER["pose_rate_hz"]))
STEP_US = 1000
# single-pose noise of the oracle, RMS over the three axes: 1 cm per axis, 0.03 rad per axis
POSE_NOISE_CM = 100 * ORACLE_NOISE["std_translation"] * np.sqrt(3)
POSE_NOISE_DEG = np.degrees(ORACLE_NOISE["std_rotation"] * np.sqrt(3))

OUTLIER_SEED = 27
"""Oracle seed of the rest sequence: frames 308, 908, 1008 and 1308 ms are outliers at a 10%
rate (the first pose is an inlier: a filter has nothing to gate its first pose against)."""


def _on_grid(t_us: int) -> int:
    """The end of the velocity step in which a measurement available at ``t_us`` is fused."""
    return -(-t_us // STEP_US) * STEP_US


# ---------------------------------------------------------------------------- sequences
@pytest.fixture(scope="module")
def rest_sequence(tmp_path_factory, box):
    """0.45 s of fast motion (up to 1.6 m/s and 2.5 rad/s), then a full second at rest."""
    traj = knot_trajectory(
        [0.0, 0.2, 0.45, 1.45],
        [[-0.12, 0.05, 0.65], [0.0, -0.02, 0.6], [0.1, 0.02, 0.7], [0.1, 0.02, 0.7]],
        [[0.8, -0.4, -0.2], [0.6, 0.2, 0.5], [0, 0, 0], [0, 0, 0]],
        rotvecs=[[0, 0, 0], [0.4, 0.2, 0.1], [0.7, 0.5, 0.2], [0.7, 0.5, 0.2]],
        rotvec_rates=[[2.0, 1.0, 0.5], [1.5, 1.5, 0.5], [0, 0, 0], [0, 0, 0]])
    return simulate_sequence(box, traj, 1.45, tmp_path_factory.mktemp("robust") / "rest")




class _Runs:
    """Tracker runs shared by the tests of this module."""

    def __init__(self) -> None:
        self.cache: dict[tuple, tuple] = {}

    def get(self, seq, key: str, oracle: dict, seed: int = 0, **config):
        k = (id(seq), key)
        if k not in self.cache:
            tracker, source = make_tracker(seq, seed=seed, oracle=oracle, method="full",
                                           **config)
            self.cache[k] = (tracker.track(seq), tracker, source)
        return self.cache[k]


@pytest.fixture(scope="module")
def robust_runs() -> _Runs:
    return _Runs()


# ---------------------------------------------------------------------------- pose outliers
_DEPTH_HANDLING = {  # config of each variant: the defaults, the check alone, the gate alone
    "aligned-checked": {},
    "depth-check": {"pose_gate": {"depth_align": False}},
    "gate-only": {"pose_gate": {"depth_align": False, "depth_min_share": 0.0}},
}


@pytest.mark.parametrize("handling", list(_DEPTH_HANDLING))
def test_pose_outliers_are_rejected_against_the_clean_run(rest_sequence, robust_runs,
                                                          handling) -> None:
    """10% of the poses replaced by random ones (random rotation, translation moved up to
    ±0.3 m per axis): every outlier and no inlier is rejected, before the filter by the depth
    check (``pose_gate.depth_min_share``, the default) or, without it, by the filter's gate; and a
    rejected outlier changes nothing: the run
    equals, to 1e-12, the run in which the same frames gave no pose at all. The error is then
    that of the clean run minus the information of the lost poses. With the defaults the poses
    are first moved along their rays onto the depth frames (``pose_gate.depth_align``): an outlier
    so moved can pass the depth check, and the gate must then reject it (its rotation is
    random).

    Measured: 4 outliers of 15 poses (308 ms in motion, 908 and 1008 ms in a row at rest,
    1308 ms), 4 rejected (by the depth check: all 4; by the gate alone: all 4; with the
    alignment: 3 by the check, 1 by the gate), none in the clean run; RMSE 4.37 cm / 10.96 deg
    against 3.37 / 9.22
    clean (the pose lost at 308 ms, in fast motion, costs the difference). Bounds: clean +
    1.5 cm and + 3 deg; one accepted outlier would cost tens of cm and degrees (its rotation
    is off by 120 deg on average)."""
    seq = rest_sequence
    config = _DEPTH_HANDLING[handling]
    clean, clean_tracker, _ = robust_runs.get(seq, f"clean-{handling}", ORACLE_NOISE,
                                              seed=OUTLIER_SEED, **config)
    traj, tracker, source = robust_runs.get(seq, f"outliers-{handling}",
                                            {**ORACLE_NOISE, "outlier_rate": 0.1},
                                            seed=OUTLIER_SEED, **config)
    end = int(traj.t_us[-1])
    outliers = set(source.outliers)
    assert len([t for t in outliers if t + LATENCY_US <= end]) >= 3
    assert tracker.stats.poses == clean_tracker.stats.poses
    fused_by_end = len([t for t in outliers if t + LATENCY_US <= end])
    if handling == "depth-check":
        assert tracker.stats.poses_implausible == fused_by_end
    elif handling == "gate-only":
        assert tracker.stats.poses_rejected == fused_by_end
    else:
        assert tracker.stats.poses_depth_aligned >= clean_tracker.stats.poses - fused_by_end
    assert tracker.stats.poses_rejected + tracker.stats.poses_implausible == fused_by_end
    assert clean_tracker.stats.poses_rejected == clean_tracker.stats.poses_implausible == 0
    assert tracker.stats.reinitialisations == 0 and tracker.stats.lost == 0
    # the reference: the same inlier poses, nothing at the outliers' frames
    ref_tracker, oracle = make_tracker(seq, seed=OUTLIER_SEED, method="full", **config)

    def without_outliers(t_us, rgb, depth):
        return None if t_us in outliers else oracle(t_us, rgb, depth)

    ref_tracker.pose_source = without_outliers
    ref = ref_tracker.track(seq)
    assert ref_tracker.stats.pose_misses == len(outliers)
    assert torch.equal(traj.status, ref.status)
    torch.testing.assert_close(traj.poses, ref.poses, rtol=0, atol=1e-12, equal_nan=True)
    gt = seq.ground_truth
    err, base = tracking_errors(traj, gt), tracking_errors(clean, gt)
    assert err.samples == base.samples
    assert err.position_rmse_cm < base.position_rmse_cm + 1.5
    assert err.rotation_rmse_deg < base.rotation_rmse_deg + 3.0


@pytest.mark.parametrize("agreement", [True, False])
def test_agreeing_rejected_poses_reinitialise_at_the_second(rest_sequence, agreement) -> None:
    """From 0.8 s (at rest) every pose is 0.4 m farther away, as when the filter has drifted
    off: the gate rejects the shifted poses (the innovation is over 7 sigma). With
    ``pose_gate.reinit_on_agreement`` the second shifted pose agrees with the first (same shift, the
    object at rest) and re-initialises the filter: 2 rejected, 1 re-initialisation, and the
    rest are fused. Without it the filter's ``reinit_after`` (3 in the tracker) takes the
    third. Both end on the shifted poses. (The depth frames, which show the object where it
    is, would contradict poses shifted in a sequence whose filter has not drifted: the depth
    check is off here; ``test_depth_contradicting_poses_are_dropped`` has it on.)"""
    seq = rest_sequence
    shift = np.array([0.0, 0.0, 0.4])
    tracker, oracle = make_tracker(seq, seed=OUTLIER_SEED,
                                   pose_gate={"reinit_on_agreement": agreement,
                                              "depth_min_share": 0.0})

    def shifted(t_us, rgb, depth):
        m = oracle(t_us, rgb, depth)
        if m is None or t_us < 800_000:
            return m
        pose = m.pose.clone()
        pose[:3, 3] += torch.from_numpy(shift)
        return PoseMeasurement(m.t_us, pose, m.cov, m.confidence)

    tracker.pose_source = shifted
    traj = tracker.track(seq)
    assert tracker.stats.poses_rejected == (2 if agreement else 3)
    assert tracker.stats.reinitialisations == 1 and tracker.stats.lost == 0
    truth = torch.as_tensor(seq.ground_truth.pose_at(traj.t_us[-1:]))[0]
    offset = (traj.poses[-1, :3, 3] - truth[:3, 3]).numpy()
    assert np.linalg.norm(offset - shift) < 0.03


# ---------------------------------------------------------------------------- at rest
def test_a_second_at_rest(rest_sequence, robust_runs) -> None:
    """The object stops at 0.45 s and stays still for a second: the sensor sees no event. The
    twist decays to zero (non-increasing, below 1e-9 within 50 ms of the last event: the
    velocity filter halves it every ms), the pose changes only when a pose measurement is
    fused (every 100 ms), and the error against the truth stays within the noise of one pose.
    Measured over [0.55 s, 1.45 s]: 1.28 cm / 3.02 deg; bound 1.5x the single-pose noise
    (2.60 cm / 4.47 deg). Last event at 439.7 ms; twist up to 0.94 before it."""
    seq = rest_sequence
    traj, tracker, _ = robust_runs.get(seq, "clean", ORACLE_NOISE, seed=OUTLIER_SEED)
    t_last = int(seq.events.t[-1])
    assert t_last < 450_000  # a second (and more) without events
    t = traj.t_us.numpy()
    assert (traj.status.numpy()[t >= 200_000] == STATUS_TRACKING).all()
    assert tracker.stats.lost == 0 and tracker.stats.pose_misses == 0
    # the twist decays
    norm = np.linalg.norm(traj.twists.numpy(), axis=1)
    after = t >= t_last + STEP_US * tracker.config.flow_batch_steps
    assert np.all(np.diff(norm[after]) <= 0)
    assert norm[t >= t_last + 50_000].max() < 1e-9
    assert norm[(t > 300_000) & (t < t_last)].max() > 0.1  # it was moving
    # the pose holds: it changes only at the steps where a pose measurement is fused
    rest = t >= t_last + 50_000
    poses = traj.poses[rest]
    moved = (poses[1:] - poses[:-1]).abs().flatten(1).max(1).values > 1e-9
    changed = t[rest][1:][moved.numpy()]
    fused_at = {_on_grid(int(f) + LATENCY_US) for f in seq.rgb_times_us.tolist()}
    assert len(changed) >= 8 and set(changed.tolist()) <= fused_at
    err = tracking_errors(traj, seq.ground_truth, t_start_us=550_000)
    assert err.position_rmse_cm < 1.5 * POSE_NOISE_CM
    assert err.rotation_rmse_deg < 1.5 * POSE_NOISE_DEG


# ---------------------------------------------------------------------------- event bursts


def test_event_burst_over_the_whole_sensor(fast_sequence, runs) -> None:
    """A 20 ms burst of random events over the whole sensor at 100x the sequence's mean event
    rate (105k events, 430 events per pixel per second) in the middle of the sequence: the 20
    steps are found to be a burst and none of their events reaches the flow (its work per call
    stays that of the clean run), no NaN, and after the burst the error is back near the clean
    run's. Measured after the burst: 6.62 cm / 12.52 deg against 6.33 / 12.48 clean; before
    the burst detection (the flow fed with the noise): 9.65 cm, twist up to 5 m/s. With one
    hue per face of the box (a different event stream): 5.13 cm / 10.43 deg against 3.99 /
    10.21 clean. With the tracker's flow reporting RoI windows of 2 supporting events
    (``min_support`` 2, 2026-11-26) the clean run gained more than the burst run: 6.27 cm /
    10.92 deg against 4.27 / 8.03 clean (min_support 5: 6.92 / 10.44 against 6.16 / 9.86); the
    20 steps without events cost the gap. The flow now copes with this noise when it is not
    detected (``burst_rate_hz: 0``: about as far off as detected), so the bounds check the
    recovery (no divergence), and the counts above the detection. With the flow's burst filter
    re-synchronised after the burst and the tracker's flow history 1 (2026-12-01): 6.10 cm /
    9.06 deg against 4.98 / 8.37 clean; without the re-synchronisation 6.52 / 13.60 (history
    1) and 6.87 / 10.21 (history 2): each pixel's first event after the burst started a burst
    in the filter, and those onsets made flows of 1500-2500 px/s and ω_z of -24 to -38 rad/s
    for a few ms. Bounds: clean + 3 cm and + 4 deg."""
    seq = fast_sequence
    ev = seq.events
    t0, t1 = 300_000, 320_000
    rate = len(ev) / (float(ev.t[-1] - ev.t[0]) * 1e-6)
    burst = noise_burst(ev.sensor_size, t0, t1 - t0, 100 * rate, seed=5)
    noisy = with_events(seq, merged(ev, burst))
    tracker, _ = make_tracker(noisy, method="full")
    calls = record_flow_calls(tracker)
    traj = tracker.track(noisy)
    clean, clean_tracker, _ = runs.get("full")
    st = tracker.stats
    assert clean_tracker.stats.burst_steps == 0
    assert st.burst_steps == (t1 - t0) // STEP_US
    assert st.events_in_bursts > 0.1 * len(burst)
    # no event of the burst's time reached the flow, whose calls stay those of the clean run
    assert all(c[2] < t0 or c[1] >= t1 for c in calls if c[0])
    assert max(c[0] for c in calls) < 200 * tracker.config.flow_batch_steps  # clean: < 200/step
    assert bool(torch.isfinite(traj.poses[traj.tracked]).all())
    assert bool(torch.isfinite(traj.twists).all())
    gt = seq.ground_truth
    err = tracking_errors(traj, gt, t_start_us=t1)
    ref = tracking_errors(clean, gt, t_start_us=t1)
    assert err.position_rmse_cm < ref.position_rmse_cm + 3.0
    assert err.rotation_rmse_deg < ref.rotation_rmse_deg + 4.0


def test_after_a_burst_the_flow_filter_continues_each_pixel_first_event(fast_sequence) -> None:
    """For ``flow.refractory_us`` after a burst, the first event of each pixel that reaches the
    flow is handed to :meth:`TripletFlow.continue_bursts` (once per pixel, across step groups)
    before the flow gets it, and no other event is."""
    seq = fast_sequence
    ev = seq.events
    t0, t1 = 300_000, 320_000
    rate = len(ev) / (float(ev.t[-1] - ev.t[0]) * 1e-6)
    noisy = with_events(seq, merged(ev, noise_burst(ev.sensor_size, t0, t1 - t0, 100 * rate,
                                                    seed=5)))
    tracker, _ = make_tracker(noisy, method="full")
    span = tracker.motion.flow.config.refractory_us
    log: list[tuple[str, Events]] = []
    update, cont = tracker.motion.flow.update, tracker.motion.flow.continue_bursts

    def logged_update(events, **kw):
        log.append(("update", events))
        return update(events, **kw)

    def logged_continue(events):
        log.append(("continue", events))
        return cont(events)

    tracker.motion.flow.update, tracker.motion.flow.continue_bursts = logged_update, logged_continue
    tracker.track(noisy)
    assert tracker.stats.burst_steps == (t1 - t0) // STEP_US
    marked = [e for kind, e in log if kind == "continue" and len(e)]
    assert marked, "the burst started no re-synchronisation"
    t = torch.cat([e.t for e in marked])
    pixel = torch.cat([e.y.long() * CAM_W + e.x.long() for e in marked])
    assert bool(((t >= t1) & (t < t1 + span)).all())
    assert len(torch.unique(pixel)) == len(pixel)  # once per pixel
    fed = [e for kind, e in log if kind == "update" and len(e)]
    ft = torch.cat([e.t for e in fed])
    fpix = torch.cat([e.y.long() * CAM_W + e.x.long() for e in fed])
    window = (ft >= t1) & (ft < t1 + span)
    wt, wpix = ft[window], fpix[window]
    first = {}
    for ti, pi in zip(wt.tolist(), wpix.tolist(), strict=True):
        first.setdefault(pi, ti)
    assert dict(zip(pixel.tolist(), t.tolist(), strict=True)) == first
    # each marked batch was handed over before the flow got its events, not after
    for i, (kind, e) in enumerate(log):
        if kind != "continue" or not len(e):
            continue
        covers = [j for j, (k, u) in enumerate(log) if k == "update" and len(u)
                  and int(u.t[0]) <= int(e.t[0]) <= int(u.t[-1])]
        assert covers and min(covers) > i


CAM_W = 128
CAM = PinholeCamera(100.0, 100.0, 63.5, 47.5, 128, 96)
























# ---------------------------------------------------------------------------- dropped frames
def test_dropped_rgbd_frames(fast_sequence, runs) -> None:
    """RGB-D frames dropped (the RGB and the depth frame of a time together): every frame in
    [150, 400) ms (a gap: 2 of the 6 poses lost, the depth frame too old after 250 ms) and half
    of the others at random (pose frames too: the next frame then takes the pose slot). The
    track survives on events: never lost, no NaN; in the gap the error grows (the events alone
    carry the pose) and once a pose arrives after the gap it is back to the clean run's.

    Measured: in [250, 508) ms 8.19 cm against 5.39 clean (bound: 2x clean); after the first
    pose after the gap (fused at 508 ms) 7.36 cm / 12.11 deg against 7.39 / 12.49 clean
    (bounds: clean + 1 cm and + 2 deg); 684 RoIs took the fallback depth. Half the frames
    alone (no gap): 5.81 cm / 15.9 deg against 5.76 / 15.5 over the run."""
    seq = fast_sequence
    times = seq.rgb_times_us.numpy()
    gap = (times >= 150_000) & (times < 400_000)
    dropped = gap | (np.random.default_rng(0).random(len(times)) < 0.5)
    tracker, _ = make_tracker(seq, method="full")
    traj = stream(tracker, seq, keep_frame=lambda i: not dropped[i])
    clean, clean_tracker, _ = runs.get("full")
    st = tracker.stats
    assert st.frames == 2 * int((~dropped).sum())
    assert st.lost == 0 and st.pose_misses == 0
    assert st.poses == clean_tracker.stats.poses - 2
    assert st.depth_fallbacks > 0  # no depth younger than max_depth_age_ms in the gap
    first = int(traj.t_us[traj.tracked][0])
    assert (traj.status[traj.t_us >= first] == STATUS_TRACKING).all()
    assert bool(torch.isfinite(traj.poses[traj.tracked]).all())
    gt = seq.ground_truth
    back = _on_grid(int(times[np.flatnonzero((times >= 400_000) & ~dropped)[0]]) + LATENCY_US)
    during = tracking_errors(traj, gt, 250_000, back - 1)
    ref = tracking_errors(clean, gt, 250_000, back - 1)
    assert during.position_rmse_cm < 2.0 * ref.position_rmse_cm
    err, ref = tracking_errors(traj, gt, back), tracking_errors(clean, gt, back)
    assert err.samples > 50
    assert err.position_rmse_cm < ref.position_rmse_cm + 1.0
    assert err.rotation_rmse_deg < ref.rotation_rmse_deg + 2.0


# ---------------------------------------------------------------------------- leaving the view
@pytest.mark.parametrize("setting", ["sensor", "depth_icp", "model"])
def test_leaving_and_reentering_the_view(exit_sequence, box, setting) -> None:
    """The object leaves the image for ~0.4 s. A detector finds nothing while it is out (the
    oracle answers only when at least 30% of the true silhouette is in the image): after
    ``lost_after_misses`` (3) misses in a row the tracker reports LOST, holds the last pose and
    outputs a zero twist; the first pose after the object came back re-initialises it
    ``pose_latency_ms`` after its frame, and it tracks again.

    Measured: first frame with less than 30% in view at 358 ms, last detection of the frame at
    308 ms, misses at 408, 508, 608 ms -> LOST from 708 ms at the latest (bound: the first frame
    out + 3 pose periods + the latency, 758 ms). The predicted silhouette can leave the image
    first, which declares the object lost ``lost_after_ms`` later (507 ms with
    configs/flow_fast.yaml's span bound), but not before the object really left; back in view
    with the frame at 808 ms -> tracking from 908 ms (bound: + one period + the latency, 1008
    ms). After re-initialisation: 5.93 cm / 8.61 deg RMSE, against 5.83 cm / 8.81 deg before the
    object left (bound: 1.5x the error before it left, at least 8 cm / 8 deg). The same holds
    with the mesh aligned with the depth frames (``depth_fusion.icp``): nothing is aligned while the
    object is lost, and the alignment of a half-visible object does not hold the track. And
    with model depth (``depth.source: model``): after it, 2.7-7.5 cm per 25 ms from the return
    on (2026-11-27; 19-22 cm, with the next pose gated out, while the check of the re-measured
    steps looked at 50 ms of a pose held still)."""
    depth_icp = setting == "depth_icp"
    seq = exit_sequence
    oracle = OraclePoseSource.from_sequence(seq, seed=0, **ORACLE_NOISE)
    source = VisibleOnlySource(oracle, np.asarray(box.vertices), seq.meta.event_camera, 0.3)
    tracker = Tracker.for_sequence(
        seq, TrackerConfig.from_dict({**TEST_TRACKER, "depth_fusion": {"icp": depth_icp},
                                      "depth": {"source": "model" if setting == "model"
                                      else "sensor"}}), source)
    traj = tracker.track(seq)
    st = tracker.stats
    assert (st.depth_alignments > 10) == depth_icp
    calls, answered = source.calls, set(source.answered)
    missed = [t for t in calls if t not in answered]
    assert st.pose_misses == len(missed) >= 3 and st.lost == 1
    # the three misses in a row and the first detection after them
    k = next(i for i in range(len(calls) - 2)
             if all(c not in answered for c in calls[i:i + 3]))
    t_lost = _on_grid(calls[k + 2] + LATENCY_US)
    back = next(c for c in calls[k + 3:] if c in answered)
    t_back = _on_grid(back + LATENCY_US)
    t, status = traj.t_us.numpy(), traj.status.numpy()
    sil = Silhouette(np.asarray(box.vertices), seq.meta.event_camera)
    gt = seq.ground_truth
    frames = seq.rgb_times_us.numpy()
    visible = [sil.polygon(gt.pose_at(int(f)).numpy()).visible_fraction for f in frames]
    out = frames[np.asarray(visible) < 0.3]
    lost = np.flatnonzero(status == STATUS_LOST)
    # lost by the misses at the latest, never before the object left the view
    assert int(out.min()) <= t[lost[0]] <= t_lost and t[lost[-1]] == t_back - STEP_US
    assert (status[(t >= t[lost[0]]) & (t < t_back)] == STATUS_LOST).all()
    assert (status[t >= t_back] == STATUS_TRACKING).all()
    # re-initialised within one pose period plus the latency of the object's return
    returned = int(frames[(frames > out.min()) & (np.asarray(visible) >= 0.3)][0])
    assert t_back <= returned + PERIOD_US + LATENCY_US
    assert t_lost <= int(out.min()) + 3 * PERIOD_US + LATENCY_US
    # while lost: the last pose held, a zero twist
    held = traj.poses[status == STATUS_LOST]
    assert bool((held == held[0]).all())
    assert float(traj.twists[status == STATUS_LOST].abs().max()) == 0.0
    # tracking again after the return, as well as before the object left
    before = tracking_errors(traj, gt, t_end_us=int(out.min()))
    after = tracking_errors(traj, gt, t_start_us=t_back)
    assert after.samples > 150
    assert after.position_rmse_cm < max(1.5 * before.position_rmse_cm, 8.0)
    assert after.rotation_rmse_deg < max(1.5 * before.rotation_rmse_deg, 8.0)


# ---------------------------------------------------------------------------- bad inputs
CUBE = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])


def _pose(x: float = 0.0, z: float = 0.6) -> np.ndarray:
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


@pytest.mark.parametrize("value", [np.nan, 0.0, -1.0, np.inf])
def test_depth_frame_without_valid_pixels_uses_the_fallback(value) -> None:
    """A depth frame that is all NaN, zero, negative or infinite carries no depth: every RoI
    takes the fallback depth (the predicted depth of the object's origin) and is counted; the
    twist is that of the texture (300 px/s at 0.6 m and 100 px focal length: 1.8 m/s)."""

    ev, _ = translating_texture((128, 96), velocity=(300.0, 0.0), duration_us=15_000)
    tracker = Tracker(TrackerConfig.from_dict({"flow": {"roi_size": 16},
                                               "mask_margin_px": 200.0}),
                      camera=CAM, mesh=CUBE)
    tracker.reset(_pose(), t_us=0)
    tracker.push_frame(0, depth=np.full((96, 128), value, np.float32))
    tracker.push_events(ev)
    tracker.flush()
    st = tracker.stats
    assert st.frames_without_depth == 0 and st.roi_flows > 0
    assert st.depth_fallbacks == st.roi_flows
    assert 0.9 < tracker.twist()[0] < 2.7 and np.isfinite(tracker.pose()).all()


def test_integer_depth_frame_is_an_error() -> None:
    tracker = Tracker(TrackerConfig(), camera=CAM, mesh=CUBE)
    with pytest.raises(ValueError, match="uint16.*metres"):
        tracker.push_frame(0, depth=np.full((96, 128), 600, np.uint16))


@pytest.mark.parametrize("problem", ["nan", "scaled", "bottom", "cov"])
def test_invalid_pose_measurements_are_errors(problem) -> None:
    """A NaN pose would poison the filter for good (the gate does not reject NaN): poses and
    covariances must be finite rigid transforms; a network's invalid detection is a miss."""
    T, cov = _pose(), None
    if problem == "nan":
        T[1, 3] = np.nan
    elif problem == "scaled":
        T[:3, :3] *= 1.01
    elif problem == "bottom":
        T[3, 0] = 0.1
    else:
        cov = np.eye(6)
        cov[0, 1] = np.inf
    with pytest.raises(ValueError, match="pose measurement at t=5 µs"):
        PoseMeasurement(5, T, cov)

    class Detection:
        pose, confidence = T, 1.0

    source = NetworkPoseSource(lambda rgb: [Detection()], cov=None if cov is None
                               else torch.from_numpy(cov))
    assert source(5, np.zeros((96, 128, 3), np.uint8)) is None and source.invalid == 1


def test_a_rejected_event_chunk_changes_nothing() -> None:
    """After a chunk is refused (unsorted, or events outside the sensor) the tracker carries
    on exactly as if the chunk had never been pushed."""

    ev, _ = translating_texture((128, 96), velocity=(300.0, 0.0), duration_us=20_000)
    half = int(np.searchsorted(ev.t.numpy(), 10_000))
    config = TrackerConfig.from_dict({"flow": {"roi_size": 16}, "mask_margin_px": 200.0})
    outputs = []
    for bad in (None, "unsorted", "outside"):
        tracker = Tracker(config, camera=CAM, mesh=CUBE)
        tracker.reset(_pose(), t_us=0)
        tracker.push_events(ev[:half])
        if bad is not None:
            t = ev.t[half:half + 10].flip(0) if bad == "unsorted" else ev.t[half:half + 10]
            x = ev.x[half:half + 10].clone()
            if bad == "outside":
                x[3] = 128
            with pytest.raises(EventsError):
                tracker.push_events(Events(x, ev.y[half:half + 10], t, ev.p[half:half + 10],
                                           (128, 96)))
        tracker.push_events(ev[half:])
        tracker.flush()
        outputs.append(tracker.trajectory())
    for other in outputs[1:]:
        assert torch.equal(other.poses, outputs[0].poses)
        assert torch.equal(other.twists, outputs[0].twists)


def test_low_confidence_detections_are_misses_and_lose_the_object() -> None:
    """Detections below ``pose_gate.min_confidence`` are ignored (counted as misses); after
    ``lost_after_misses`` of them in a row the object is lost."""
    confidence = {"value": 0.9}

    def source(t_us, rgb, depth):
        return PoseMeasurement(t_us, _pose(), confidence=confidence["value"])

    config = TrackerConfig.from_dict({"method": "pose", "pose_gate": {"min_confidence": 0.5},
                                      "pose_rate_hz": 10.0, "pose_latency_ms": 0.0,
                                      "lost_after_misses": 2,
                                      "flow_batch_steps": 5})  # advance() closes 5 ms groups
    tracker = Tracker(config, camera=CAM, mesh=CUBE, pose_source=source)
    rgb = np.zeros((96, 128, 3), np.uint8)
    tracker.push_frame(0, rgb=rgb)
    tracker.advance(5_000)
    assert tracker.status == STATUS_TRACKING
    confidence["value"] = 0.2
    tracker.push_frame(100_000, rgb=rgb)
    tracker.advance(105_000)
    assert tracker.status == STATUS_TRACKING and tracker.stats.pose_misses == 1
    tracker.push_frame(200_000, rgb=rgb)
    tracker.advance(205_000)
    assert tracker.status == STATUS_LOST and tracker.stats.lost == 1
    assert tracker.stats.poses == 1 and tracker.stats.pose_misses == 2
    np.testing.assert_allclose(tracker.pose(), _pose(), atol=1e-9)  # held


def test_depth_contradicting_poses_are_dropped(rest_sequence) -> None:
    """The shifted poses of ``test_agreeing_rejected_poses_reinitialise_at_the_second`` (0.4 m
    farther from 0.8 s, the object at rest) against depth frames that show the object where
    it is: with the depth check (the default ``pose_gate.depth_min_share``) none of them reaches
    the filter, so nothing is rejected or re-initialised and the track stays on the object,
    where the unchecked filter ends 0.4 m off."""
    seq = rest_sequence
    tracker, oracle = make_tracker(seq, seed=OUTLIER_SEED)
    shifted_times: list[int] = []

    def shifted(t_us, rgb, depth):
        m = oracle(t_us, rgb, depth)
        if m is None or t_us < 800_000:
            return m
        shifted_times.append(t_us)
        pose = m.pose.clone()
        pose[:3, 3] += torch.tensor([0.0, 0.0, 0.4], dtype=pose.dtype)
        return PoseMeasurement(m.t_us, pose, m.cov, m.confidence)

    tracker.pose_source = shifted
    traj = tracker.track(seq)
    fused_by_end = [t for t in shifted_times if t + LATENCY_US <= int(traj.t_us[-1])]
    assert len(fused_by_end) >= 3
    assert tracker.stats.poses_implausible == len(fused_by_end)
    assert tracker.stats.poses_rejected == tracker.stats.reinitialisations == 0
    truth = torch.as_tensor(seq.ground_truth.pose_at(traj.t_us[-1:]))[0]
    assert float(torch.linalg.vector_norm(traj.poses[-1, :3, 3] - truth[:3, 3])) < 0.03


@pytest.mark.parametrize("late_ms", [0, 80, 250])
def test_a_pushed_pose_is_checked_against_the_depth_of_its_time(rest_sequence, late_ms) -> None:
    """Streaming, poses handed in by the caller (:meth:`Tracker.push_pose`, no pose source)
    ``late_ms`` after their frame, as a caller's own network delivers them, while the object
    moves along the camera's axis at ~0.4 m/s. The depth check and the alignment read the
    depth frame of the pose's time, not the latest one: 80 ms on, the latest lies ~3 cm
    farther (aligned onto it, the pose would be that far off); 250 ms on, it is older than
    ``depth.max_age_ms`` allows. A pose 0.4 m behind the object is dropped; the true pose
    moved 5 cm along its ray is aligned to within 1 cm of the truth and starts the track.
    Only the depth maps of the last ``history_ms`` (here 300 ms) are kept."""
    seq = rest_sequence
    tracker, _ = make_tracker(seq, history_ms=300.0)
    tracker.pose_source = None
    checked: list[PoseMeasurement | None] = []
    gate = tracker.pose_gate
    depth_checked = gate.depth_checked
    gate.depth_checked = lambda m: checked.append(depth_checked(m)) or checked[-1]
    times = seq.depth_times_us.numpy()
    i = int(np.argmin(np.abs(times - 300_000)))
    t_pose = int(times[i])
    truth = torch.as_tensor(seq.ground_truth.pose_at(t_pose))
    later = seq.ground_truth.pose_at(t_pose + late_ms * 1000)
    if late_ms:  # moving away: the test's premise
        assert later[2, 3] - truth[2, 3] > 0.025
    stream(tracker, seq, t_end_us=t_pose + late_ms * 1000 + 1)
    far = truth.clone()
    far[:3, 3] += torch.tensor([0.0, 0.0, 0.4], dtype=far.dtype)
    tracker.push_pose(PoseMeasurement(t_pose, far))
    tracker.flush()
    assert checked == [None] and tracker.stats.poses_implausible == 1
    assert not tracker.initialized
    off = truth.clone()
    off[:3, 3] *= 1.0 + 0.05 / float(torch.linalg.vector_norm(truth[:3, 3]))
    tracker.push_pose(PoseMeasurement(t_pose, off))
    tracker.flush()
    assert tracker.initialized and tracker.stats.poses_depth_aligned == 1
    error = float(torch.linalg.vector_norm(checked[-1].pose[:3, 3] - truth[:3, 3]))
    assert error < 0.01
    # the kept maps: the frames of the last history_ms, no more (memory stays bounded)
    kept = sorted(tracker.pose_gate.depth_frames)
    newest = int(times[times < t_pose + late_ms * 1000 + 1].max())
    span_us = tracker.config.history_ms * 1000
    assert kept[-1] == newest and kept[0] > 0 and kept[-1] - kept[0] <= span_us
    assert len(kept) == int(((times >= newest - span_us) & (times <= newest)).sum())


@pytest.mark.parametrize("case", ["on", "off", "below-confidence", "below-alternatives-least"])
def test_a_dropped_pose_gives_way_to_an_alternative_the_depth_confirms(rest_sequence, case
                                                                       ) -> None:
    """Streaming, the object at rest: the pose handed in lies 0.4 m behind the object (the
    depth drops it) and carries two alternatives, one 0.5 m in front (dropped as well) and
    the true pose 5 cm off along its ray. With ``pose_gate.alternatives`` (the default) the
    second alternative is aligned, starts the track within 1 cm of the truth and is counted
    in ``poses_from_alternatives``, not as implausible; off, or with the alternatives below
    ``pose_gate.min_confidence`` or ``pose_gate.alternatives_min_confidence`` (0.3), the pose is
    dropped and the filter stays uninitialised."""
    seq = rest_sequence
    settings = {"off": {"pose_gate": {"alternatives": False}},
                "below-confidence": {"pose_gate": {"min_confidence": 0.5}}}.get(case, {})
    tracker, _ = make_tracker(seq, **settings)
    tracker.pose_source = None
    t_pose = int(seq.depth_times_us[-5])
    stream(tracker, seq, t_end_us=t_pose + 1)
    truth = torch.as_tensor(seq.ground_truth.pose_at(t_pose))

    def along_ray(shift_m: float) -> torch.Tensor:
        pose = truth.clone()
        pose[:3, 3] *= 1.0 + shift_m / float(torch.linalg.vector_norm(truth[:3, 3]))
        return pose

    alt_confidence = {"below-confidence": 0.4, "below-alternatives-least": 0.2}.get(case, 0.6)
    alternatives = (PoseMeasurement(t_pose, along_ray(-0.5), confidence=alt_confidence),
                    PoseMeasurement(t_pose, along_ray(0.05), confidence=alt_confidence))
    tracker.push_pose(PoseMeasurement(t_pose, along_ray(0.4), confidence=0.9,
                                      alternatives=alternatives))
    tracker.flush()
    if case != "on":
        assert not tracker.initialized
        assert tracker.stats.poses_implausible == 1 and tracker.stats.poses_from_alternatives == 0
        return
    assert tracker.initialized and tracker.stats.poses_implausible == 0
    assert tracker.stats.poses_from_alternatives == 1 and tracker.stats.poses_depth_aligned == 1
    error = float(torch.linalg.vector_norm(torch.as_tensor(tracker.pose(t_pose))[:3, 3]
                                           - truth[:3, 3]))
    assert error < 0.01


def test_pose_measurement_alternatives_are_validated() -> None:
    """Alternatives must be measurements of the same time without alternatives of their own."""
    pose = torch.eye(4, dtype=torch.float64)
    pose[2, 3] = 1.0
    alt = PoseMeasurement(10, pose)
    assert PoseMeasurement(10, pose, alternatives=[alt]).alternatives == (alt,)
    for bad in ([PoseMeasurement(11, pose)], [pose],
                [PoseMeasurement(10, pose, alternatives=(alt,))]):
        with pytest.raises(ValueError, match="alternative"):
            PoseMeasurement(10, pose, alternatives=bad)


@pytest.mark.parametrize("align", [True, False])
def test_a_pose_off_in_range_is_moved_onto_the_depth(rest_sequence, align) -> None:
    """Streaming, the object at rest: the first pose handed in is the true one moved 5 cm
    farther along its viewing ray, as an RGB network errs. With ``pose_gate.depth_align`` (the
    default) it is moved onto the depth frame of its time and the filter starts within 1 cm of
    the truth (measured: 1.5 mm); without, 5 cm off (the depth check passes it: its 6 cm
    tolerance). The true pose itself is moved by under 5 mm."""
    seq = rest_sequence
    tracker, _ = make_tracker(seq, pose_gate={"depth_align": align})
    tracker.pose_source = None
    t_pose = int(seq.depth_times_us[-5])
    stream(tracker, seq, t_end_us=t_pose + 1)
    truth = torch.as_tensor(seq.ground_truth.pose_at(t_pose))
    exact = PoseMeasurement(t_pose, truth)  # the truth itself: the alignment must keep it
    far = truth.clone()
    far[:3, 3] *= 1.0 + 0.05 / float(torch.linalg.vector_norm(truth[:3, 3]))
    tracker.push_pose(PoseMeasurement(t_pose, far))
    tracker.flush()
    assert tracker.initialized and tracker.stats.poses_implausible == 0
    assert tracker.stats.poses_depth_aligned == int(align)
    error = float(torch.linalg.vector_norm(torch.as_tensor(tracker.pose(t_pose))[:3, 3]
                                           - truth[:3, 3]))
    if align:
        assert error < 0.01
    else:
        assert error > 0.045
    aligner = tracker.pose_gate.aligner or Tracker.for_sequence(seq,
                                                                TrackerConfig()).pose_gate.aligner
    res = aligner.align(seq.depth(len(seq.depth_times_us) - 5), exact.pose)
    assert res.ok and abs(res.shift) < 0.005








