"""The event gate (evtrack.tracking.event_gate): thinning by whole RoI cells in a fixed order
with hysteresis, the swept silhouette mask, and the float path that moves a pose by a twist."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from tracker_helpers import make_tracker

from evtrack.camera import PinholeCamera
from evtrack.events import Events, concatenate
from evtrack.flow import TripletFlow
from evtrack.flow.scenes import translating_texture
from evtrack.geometry import integrate_twist
from evtrack.tracking import event_gate
from evtrack.tracking.event_gate import EventGate, moved_pose
from evtrack.tracking.silhouette import Silhouette

CAM = PinholeCamera(100.0, 100.0, 63.5, 47.5, 128, 96)
CUBE = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])


def _gate(camera: PinholeCamera, roi_size: int) -> EventGate:
    return EventGate(camera, Silhouette(CUBE, camera), mask_margin_px=8.0, burst_rate_hz=100.0,
                     roi_size=roi_size)


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _cells_of(gate: EventGate, ev: Events) -> np.ndarray:
    s = event_gate.THIN_CELL_ROIS * gate.roi_size
    cols = -(-gate.camera.width // s)
    return (ev.y.numpy().astype(np.int64) // s) * cols + ev.x.numpy().astype(np.int64) // s


def test_thinning_keeps_whole_cells_in_a_fixed_order_with_hysteresis() -> None:
    """The budget keeps whole cells of 2 x 2 RoIs (every event of a cell or none), a prefix of
    one fixed order, ``int(n_cells * 0.75**level)`` of them; the level rises as far as needed,
    stays while the next lower level does not fit in 80 % of the budget, and falls back to 0
    (no thinning) once everything fits."""
    gate = _gate(CAM, roi_size=8)  # 128x96: 8 x 6 cells of 2 x 2 RoIs
    assert event_gate.THIN_CELL_ROIS == 2
    rng = np.random.default_rng(0)

    def random_events(n: int) -> Events:
        return Events(rng.integers(0, 128, n), rng.integers(0, 96, n), np.arange(n),
                      rng.integers(0, 2, n), CAM.size)

    def per_cell(m: int) -> Events:  # m events in every cell
        cx, cy = np.meshgrid(np.arange(8), np.arange(6))
        x = np.repeat(16 * cx.ravel() + 8, m)
        y = np.repeat(16 * cy.ravel() + 8, m)
        return Events(x, y, np.arange(len(x)), np.zeros(len(x), np.int64), CAM.size)

    ev = random_events(4000)
    kept = gate.thin(ev, 1000)
    cells, all_cells = _cells_of(gate, kept), _cells_of(gate, ev)
    taken = np.unique(cells)
    assert 0 < len(kept) <= 1000 and gate.stats.events_thinned == len(ev) - len(kept)
    assert len(taken) == int(48 * 0.75 ** gate.thin_level)
    for c in taken:
        assert (cells == c).sum() == (all_cells == c).sum()  # whole cells
    # the same cells come first in the next group, whatever its events
    again = gate.thin(random_events(4000), 1000)
    assert set(np.unique(_cells_of(gate, again))) == set(taken)
    # levels keep 48, 36, 27, 20, 15, ... cells; 20 events per cell, budget 300: 15 cells
    gate.thin_level = 0
    assert len(gate.thin(per_cell(20), 300)) == 300 and gate.thin_level == 4
    # 14 per cell: 20 cells (280) fit the budget but not 80 % of it (240): level 4 stays
    assert len(gate.thin(per_cell(14), 300)) == 15 * 14 and gate.thin_level == 4
    # 11 per cell: down as far as fits in 240 (20 cells; 27 would be 297)
    assert len(gate.thin(per_cell(11), 300)) == 20 * 11 and gate.thin_level == 3
    # 4 per cell (192 events): back to level 0, nothing thinned
    assert len(gate.thin(per_cell(4), 300)) == 192 and gate.thin_level == 0
    # a budget below any cell's events keeps nothing
    assert len(gate.thin(per_cell(20), 10)) == 0


def test_thinning_by_cells_keeps_the_flow_of_the_kept_rois() -> None:
    """A dense texture translating at (900, -400) px/s, thinned to 1/4 of its events per
    10 ms group: the RoI flows of the kept cells are as accurate as without thinning (median
    relative endpoint error 0.036 against 0.038 measured; bound 0.045; with cells of one RoI
    instead of 2 x 2 it was 0.069: a kept RoI's border events need their neighbours), while
    keeping a quarter of single events (the smallest hashes, the former rule) leaves gaps in
    every edge's trail that the triplet search fills with unrelated older events (0.182
    measured; bound: above 0.08)."""
    W, H = 96, 72
    velocity = np.array([900.0, -400.0])
    ev, _ = translating_texture((W, H), velocity=tuple(velocity), duration_us=40_000, seed=3)
    camera = PinholeCamera(80.0, 80.0, (W - 1) / 2, (H - 1) / 2, W, H)
    gate = _gate(camera, roi_size=12)
    starts = range(0, 40_000, 10_000)
    budget = len(ev) // len(starts) // 4
    by_cells = concatenate([gate.thin(ev.between(t, t + 10_000), budget) for t in starts])
    index = np.arange(len(ev), dtype=np.uint64)
    with np.errstate(over="ignore"):
        hashed = index * np.uint64(0x9E3779B97F4A7C15)
    keep = np.zeros(len(ev), bool)
    t = ev.t.numpy()
    for t0 in starts:
        group = np.flatnonzero((t >= t0) & (t < t0 + 10_000))
        keep[group[np.argsort(hashed[group], kind="stable")[:budget]]] = True
    single = ev[torch.from_numpy(keep)]

    def median_error(events: Events) -> float:
        res = TripletFlow(roi_size=12, window_us=2000)(events)
        err = np.linalg.norm(res.flow.numpy() - velocity, axis=1) / np.linalg.norm(velocity)
        return float(np.median(err))

    assert len(by_cells) <= len(starts) * budget and len(single) == len(starts) * budget
    whole, cells, singles = median_error(ev), median_error(by_cells), median_error(single)
    print(f"median relative error: all {whole:.3f}, cells {cells:.3f}, single events "
          f"{singles:.3f}")
    assert cells < 0.045 and cells < whole + 0.01
    assert singles > 0.08


def _mask_coverage(seq, monkeypatch, swept: bool) -> tuple[float, int]:
    """Share of the object's events (inside the true silhouette at their time, 1 px margin)
    that the tracker's event masks kept, over the step groups it masked; and their number."""
    masks = []
    sweep, on_object = EventGate.swept_mask, EventGate.on_object
    group: list[int] = []

    def gating(self, ev, t0, t_end, *args):
        group[:] = [t0]
        return on_object(self, ev, t0, t_end, *args)

    def recording(self, poly, pose, span_us, twist):
        mask = sweep(self, poly, pose, span_us, twist) if swept else poly
        masks.append((group[0], group[0] + span_us, mask))
        return mask

    monkeypatch.setattr(EventGate, "on_object", gating)
    monkeypatch.setattr(EventGate, "swept_mask", recording)
    tracker, _ = make_tracker(seq, method="full")
    tracker.track(seq)
    monkeypatch.undo()
    ev = seq.events
    x, y, t = ev.x.numpy(), ev.y.numpy(), ev.t.numpy()
    sil, size, margin = tracker.silhouette, tracker.camera.size, tracker.config.mask_margin_px
    hit = total = 0
    for t0, t1, mask in masks:
        lo, hi = np.searchsorted(t, [t0, t1])
        keep = mask.contains_pixels(x[lo:hi], y[lo:hi], margin, size)
        on_object = np.zeros(hi - lo, bool)
        for a in range(t0, t1, 2000):  # the true silhouette every 2 ms
            sel = (t[lo:hi] >= a) & (t[lo:hi] < a + 2000)
            poly = sil.polygon(seq.ground_truth.pose_at(a + 1000).numpy())
            if sel.any() and poly is not None:
                on_object[sel] = poly.contains_pixels(x[lo:hi][sel], y[lo:hi][sel], 1.0, size)
        hit += int((keep & on_object).sum())
        total += int(on_object.sum())
    assert total > 1000
    return hit / total, total


def test_the_group_mask_sweeps_with_the_object(fast_sequence, monkeypatch):
    """A step group's events are masked with the hull of the silhouettes predicted at its
    start and at its end (EventGate.swept_mask): with 40 ms groups and the tests' 8 px margin
    the object moves out of its starting silhouette within a group, and the start's
    silhouette alone loses the events of its leading edges."""
    swept, n = _mask_coverage(fast_sequence, monkeypatch, swept=True)
    start_only, n0 = _mask_coverage(fast_sequence, monkeypatch, swept=False)
    print(f"object events kept: swept {swept:.4f} of {n}, start only {start_only:.4f} of {n0}")
    # measured 0.995 and 0.990 on two installs whose renders differ in their last bits (start
    # only: 0.967 and 0.957); the margin is for that spread
    assert swept > 0.98
    assert swept > start_only + 0.02


def test_moved_pose_equals_integrate_twist() -> None:
    """The tracker's float path for one pose moved by a twist (``moved_pose``) against the
    tensor one (kornia's SE(3) exponential), large and tiny rotations, either sign of dt."""

    rng = np.random.default_rng(4)
    for scale in (5.0, 1e-5, 0.0):
        for dt in (0.04, -0.013, 0.0):
            T = _pose(rng.normal(size=3), rng.normal(size=3))
            twist = rng.normal(size=6) * np.array([1, 1, 1, scale, scale, scale])
            ref = integrate_twist(torch.from_numpy(T), torch.from_numpy(twist), dt).numpy()
            np.testing.assert_allclose(moved_pose(T, twist, dt), ref, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------- event bursts
STEP = 1000  # µs


def _burst_gate(baseline_us: int, factor: float = 4.0) -> tuple[EventGate, object]:
    cam = PinholeCamera(100.0, 100.0, 63.5, 47.5, 128, 96)
    gate = EventGate(cam, Silhouette(CUBE, cam), mask_margin_px=4.0, burst_rate_hz=100.0,
                     roi_size=8, burst_baseline_us=baseline_us, burst_factor=factor)
    poly = gate.silhouette.polygon(_pose([0, 0, 0], [0, 0, 1.0]))
    return gate, poly


def _outside_per_step(gate: EventGate, poly) -> float:
    w, h = gate.camera.size
    return w * h - gate._mask_area(poly)


def _step_events(counts: np.ndarray, t0: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Times of ``counts[k]`` off-object events in each step ``k`` from ``t0``, all off the
    object (the burst test only counts them)."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([np.sort(rng.integers(t0 + k * STEP, t0 + (k + 1) * STEP, n))
                        for k, n in enumerate(counts)]).astype(np.int64)
    return t, np.zeros(len(t), bool)


def _bursts(gate: EventGate, poly, rates_hz: np.ndarray, group_steps: int) -> np.ndarray:
    """The burst decision of every step for per-step off-object rates (events/px/s), fed in
    groups of ``group_steps`` steps."""
    per_step = _outside_per_step(gate, poly) * STEP * 1e-6
    counts = np.round(np.asarray(rates_hz) * per_step).astype(int)
    out = []
    for g in range(0, len(counts), group_steps):
        c = counts[g:g + group_steps]
        t, on_obj = _step_events(c, g * STEP, seed=g)
        hit = gate.in_burst(t, on_obj, poly, g * STEP, (g + len(c)) * STEP, STEP)
        cuts = np.cumsum([0, *c])
        out += [bool(hit[a:b].all()) if b > a else False
                for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    return np.array(out)


def test_a_flicker_over_a_quiet_background_is_a_burst() -> None:
    rates = np.full(200, 1.0)
    rates[120:125] = 400.0
    for baseline in (100_000, 0):
        gate, poly = _burst_gate(baseline)
        burst = _bursts(gate, poly, rates, 40)
        assert np.flatnonzero(burst).tolist() == list(range(120, 125))


def test_a_moving_cameras_background_is_not_a_burst_but_a_flicker_on_it_is() -> None:
    """Off-object activity at 300 events/px/s all the time (a moving camera's textured
    background): not a burst, from the first step on; the absolute test alone
    (``burst_baseline_ms: 0``) drops every step. A 2,000 events/px/s flicker on top of it is
    a burst."""
    rates = np.full(240, 300.0)
    rates[150:154] = 2000.0
    gate, poly = _burst_gate(100_000)
    burst = _bursts(gate, poly, rates, 40)
    assert np.flatnonzero(burst).tolist() == [150, 151, 152, 153]
    absolute, poly = _burst_gate(0)
    assert _bursts(absolute, poly, rates, 40).all()


def test_burst_decisions_match_a_running_median_reference_in_any_grouping() -> None:
    """Random background changes and flickers: each step's decision equals the reference
    (rate > 100 and rate > 4 x the median of the steps starting in the last 100 ms, this one
    included), whether the steps come in groups of 40, 10 or 7."""
    rng = np.random.default_rng(7)
    levels = np.repeat(rng.choice([0.5, 80.0, 300.0, 900.0], 8), 60)
    rates = levels * rng.uniform(0.7, 1.3, len(levels))
    flick = rng.choice(len(rates), 25, replace=False)
    rates[flick] *= rng.uniform(2.0, 12.0, len(flick))
    gate, poly = _burst_gate(100_000)
    per_step = _outside_per_step(gate, poly) * STEP * 1e-6
    measured = np.round(rates * per_step) / per_step  # the rates the gate sees
    ref = np.array([measured[k] > 100.0
                    and measured[k] > 4.0 * np.median(measured[max(0, k - 99):k + 1])
                    for k in range(len(measured))])
    assert 10 < ref.sum() < len(ref) - 10
    for group in (40, 10, 7):
        gate, poly = _burst_gate(100_000)
        np.testing.assert_array_equal(_bursts(gate, poly, rates, group), ref)


def test_reset_forgets_the_background() -> None:
    gate, poly = _burst_gate(100_000)
    _bursts(gate, poly, np.full(80, 300.0), 40)
    gate.reset()
    assert len(gate._rate) == 0
    rates = np.full(20, 1.0)
    rates[10] = 300.0  # without the reset, the 300s before would still be the background
    assert np.flatnonzero(_bursts(gate, poly, rates, 40)).tolist() == [10]
