"""Late measurements: rolling back and replaying equals receiving them on time."""

from __future__ import annotations

import pytest
import torch

from evtrack.filters import PoseTwistUKF, PoseUKF, PoseUKFConfig
from evtrack.tracking.pose_timeline import PoseTimeline

STEP = 1000


def _plain() -> PoseUKF:
    return PoseUKF(1, dtype=torch.float64)


def _biased() -> PoseUKF:
    """A filter with a velocity bias in its state (one more state tensor, ``bias``)."""
    return PoseUKF(1, PoseUKFConfig(velocity_bias=True, init_std_velocity_bias=0.2),
                   dtype=torch.float64)


FILTERS = [pytest.param(_plain, id="plain"), pytest.param(_biased, id="velocity_bias")]


def _twists(n: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return torch.randn(n, 1, 6, generator=g, dtype=torch.float64) * 0.5


def _meas(k: int):
    g = torch.Generator().manual_seed(100 + k)
    t = torch.tensor([[0.0, 0.0, 0.8]], dtype=torch.float64) + 0.02 * torch.randn(
        1, 3, generator=g, dtype=torch.float64)
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64) + 0.05 * torch.randn(
        1, 4, generator=g, dtype=torch.float64)
    return t, q / q.norm()


def _start(filt):
    filt.reset(1, t=torch.tensor([[0.0, 0.0, 0.8]], dtype=torch.float64),
               q=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64))


def _on_time_reference(twists: torch.Tensor, times, fuse, make=_plain) -> PoseUKF:
    """A plain filter (from ``make``) stepped through ``twists`` (one per STEP µs) that calls
    ``fuse(filter, t_us)`` at each measurement time of ``times`` when that time comes."""
    ref = make()
    _start(ref)
    t_cur = 0
    for k in range(len(twists)):
        t_end = (k + 1) * STEP
        for tm in sorted(times):
            if t_cur < tm <= t_end:
                ref.predict(twists[k], (tm - t_cur) * 1e-6)
                fuse(ref, tm)
                t_cur = tm
        ref.predict(twists[k], (t_end - t_cur) * 1e-6)
        t_cur = t_end
    return ref


@pytest.mark.parametrize("make", FILTERS)
def test_late_poses_equal_on_time_poses(make) -> None:
    n = 60
    twists = _twists(n)
    times = {2300: 0, 17000: 1, 17000 + 1: 2, 40500: 3}  # µs -> measurement id
    # reference: a plain filter, measurements fused when their time comes
    ref = _on_time_reference(twists, times, lambda f, tm: f.update(*_meas(times[tm])), make)
    # timeline: every measurement arrives 12 ms late, two of them in reverse order
    filt = make()
    _start(filt)
    line = PoseTimeline(filt, horizon_us=30_000)
    arrivals = sorted((tm + 12_000, -tm if tm == 17001 else tm) for tm in times)
    for k in range(n):
        line.step((k + 1) * STEP, twists[k])
        for avail, key in arrivals:
            if k * STEP < avail <= (k + 1) * STEP:
                tm = abs(key)
                assert line.add(tm, "pose", _meas(times[tm]))
    torch.testing.assert_close(filt.t, ref.t, rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.q, ref.q, rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.cov, ref.cov, rtol=1e-9, atol=1e-15)
    assert int(filt.rejected[0]) == int(ref.rejected[0])
    if make is _biased:  # the bias was learnt from the late poses as from the on-time ones
        assert "bias" in line.names and float(filt.bias.abs().max()) > 1e-3
        torch.testing.assert_close(filt.bias, ref.bias, rtol=0, atol=1e-12)


def test_late_ranges_equal_on_time_ranges() -> None:
    """A range measurement (kind ``"range"``) that arrives late is fused at its own time, as a
    plain filter would have fused it then, between the poses."""
    n = 40
    twists = _twists(n)
    u = torch.tensor([[0.1, -0.2, 1.0]], dtype=torch.float64)
    u = u / u.norm()
    ranges = {5200: 0.004, 21000: -0.006}  # µs -> offset of the measured distance (m)
    var = torch.tensor([4e-6], dtype=torch.float64)

    def measured(f: PoseUKF, offset: float) -> torch.Tensor:
        return (u * f.t).sum(-1) + offset

    values = {}

    def fuse(f: PoseUKF, tm: int) -> None:
        values[tm] = measured(f, ranges[tm])
        assert bool(f.update_range(u, values[tm], var)[0])

    ref = _on_time_reference(twists, ranges, fuse)
    filt = PoseUKF(1, dtype=torch.float64)
    _start(filt)
    line = PoseTimeline(filt, horizon_us=30_000)
    for k in range(n):
        line.step((k + 1) * STEP, twists[k])
        for tm in ranges:
            if k * STEP < tm + 9_000 <= (k + 1) * STEP:
                assert line.add(tm, "range", (u, values[tm]), var)
    torch.testing.assert_close(filt.t, ref.t, rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.q, ref.q, rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.cov, ref.cov, rtol=1e-9, atol=1e-15)
    plain = PoseUKF(1, dtype=torch.float64)
    _start(plain)
    for k in range(n):
        plain.predict(twists[k], STEP * 1e-6)
    assert float((filt.t - plain.t).abs().max()) > 1e-3  # the ranges did something


def test_twist_measurements_on_the_constant_velocity_filter() -> None:
    ref, filt = PoseTwistUKF(1), PoseTwistUKF(1)
    for f in (ref, filt):
        _start(f)
    line = PoseTimeline(filt, horizon_us=20_000)
    z = torch.tensor([[0.3, -0.1, 0.0, 0.0, 1.0, 0.5]], dtype=torch.float64)
    for k in range(10):
        ref.predict(STEP * 1e-6)
        if k == 3:
            ref.update_twist(z)
        line.step((k + 1) * STEP)
    line.add(4 * STEP, "twist", (z,))
    torch.testing.assert_close(filt.t, ref.t, rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.twist, ref.twist, rtol=0, atol=1e-12)


def test_too_late_is_dropped() -> None:
    filt = PoseUKF(1)
    _start(filt)
    line = PoseTimeline(filt, horizon_us=5_000)
    for k in range(20):
        line.step((k + 1) * STEP, torch.zeros(1, 6, dtype=torch.float64))
    before = filt.t.clone()
    assert not line.add(10_000, "pose", _meas(0))
    assert line.late == 1 and torch.equal(filt.t, before)


def test_pose_at_a_past_time_equals_a_plain_filter_stopped_there() -> None:
    # the constant-velocity filter after a twist measurement: its pose at 4.4 ms, asked after
    # 10 ms of steps, is the pose a plain filter has when predicted exactly to 4.4 ms
    z = torch.tensor([[0.3, -0.1, 0.2, 0.5, 1.0, -0.5]], dtype=torch.float64)
    ref, filt = PoseTwistUKF(1), PoseTwistUKF(1)
    for f in (ref, filt):
        _start(f)
    line = PoseTimeline(filt, horizon_us=20_000)
    for k in range(10):
        line.step((k + 1) * STEP)
    line.add(2 * STEP, "twist", (z,))
    for dt in (STEP, STEP, None, STEP, STEP, 400):  # the timeline's steps; None: the twist
        if dt is None:
            ref.update_twist(z)
        else:
            ref.predict(dt * 1e-6)
    t, q = line.pose_at(4_400)
    torch.testing.assert_close(t, ref.t[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(q, ref.q[0], rtol=0, atol=1e-12)
    # the twist-driven filter: the step's own twist carries the pose inside the step
    twists = _twists(10)
    ref, filt = PoseUKF(1), PoseUKF(1)
    for f in (ref, filt):
        _start(f)
    line = PoseTimeline(filt, horizon_us=20_000)
    for k in range(10):
        line.step((k + 1) * STEP, twists[k])
    for k in range(6):
        ref.predict(twists[k], STEP * 1e-6)
    ref.predict(twists[6], 0.3e-3)
    t, q = line.pose_at(6_300)
    torch.testing.assert_close(t, ref.t[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(q, ref.q[0], rtol=0, atol=1e-12)
    assert line.pose_at(10_001) is None and line.pose_at(-1) is None
    # before the filter has a pose there is none
    fresh = PoseTwistUKF(1)
    empty = PoseTimeline(fresh, horizon_us=20_000)
    empty.step(STEP)
    assert empty.pose_at(500) is None


def test_snapshots_are_not_changed_by_in_place_writes_to_the_filter() -> None:
    """Snapshots share the copy of a state tensor that did not change since the last one;
    a write in place into the filter (``load_state_dict`` copies into the buffers) changes
    the tensor's version, so the next snapshot copies it again and the earlier ones keep the
    old values. Also with inference tensors (no version counter: always copied)."""
    for mode in (torch.no_grad, torch.inference_mode):
        with mode():
            filt = PoseUKF(1, dtype=torch.float64)
            _start(filt)
            line = PoseTimeline(filt, horizon_us=30_000)
            twist = torch.zeros(1, 6, dtype=torch.float64)
            line.step(STEP, twist)
            before = filt.t.clone()
            counters = line._snaps[-1][line.names.index("rejected")]
            line.step(2 * STEP, twist)
            # the counters did not change: the two snapshots share one copy
            assert line._snaps[-1][line.names.index("rejected")] is counters or mode is \
                torch.inference_mode
            moved = {k: v.clone() for k, v in filt.state_dict().items()}
            moved["t"] += 0.5
            moved["rejected"] += 3
            filt.load_state_dict(moved)  # in place into the buffers
            line.step(3 * STEP, twist)
            assert float(line._snaps[-1][line.names.index("t")][0, 2]) == float(before[0, 2]) + 0.5
            assert int(line._snaps[-1][line.names.index("rejected")][0]) == 3
            # the earlier snapshots kept their values: a replay from step 1 starts from them
            assert torch.equal(line._snaps[1][line.names.index("t")], before)
            assert int(line._snaps[2][line.names.index("rejected")][0]) == 0
            line.add(1500, "pose", (before, torch.tensor([[1.0, 0.0, 0.0, 0.0]],
                                                         dtype=torch.float64)))
            assert abs(float(filt.t[0, 2]) - float(before[0, 2])) < 1e-3


def test_remeasured_twists_equal_a_filter_started_by_the_pose_and_driven_by_them() -> None:
    """A late first pose starts the filter at its own time; remeasure then replaces the twists
    of the steps after it: the result equals a plain filter initialised by that pose at that
    time and predicted with the new twists (the step the pose falls in keeps its old twist),
    and later late poses replay over the new twists."""
    n, t_pose, first_new = 50, 12_500, 13  # steps 13.. (t_start >= 13 ms) get new twists
    old, new = _twists(n), -2.0 * _twists(n)
    filt = PoseUKF(1, dtype=torch.float64)  # no pose yet
    line = PoseTimeline(filt, horizon_us=100_000)
    pose = _meas(0)
    for k in range(n):
        line.step((k + 1) * STEP, old[k])
        if (k + 1) * STEP == 30 * STEP:  # the pose of 12.5 ms arrives at 30 ms
            assert line.add(t_pose, "pose", pose)
    assert bool(filt.initialized[0])
    ref = PoseUKF(1, dtype=torch.float64)
    ref.update(*pose)  # initialises at t_pose
    ref.predict(old[12], (first_new * STEP - t_pose) * 1e-6)
    asked = []

    def twist_of(t_start: int, t_end: int) -> torch.Tensor:
        k = t_start // STEP
        asked.append((t_start, t_end))
        # the filter holds the state at t_start: the reference's
        torch.testing.assert_close(filt.t, ref.t, rtol=0, atol=1e-12)
        torch.testing.assert_close(filt.q, ref.q, rtol=0, atol=1e-12)
        ref.predict(new[k], STEP * 1e-6)
        return new[k]

    assert line.remeasure(t_pose, twist_of) == n - first_new
    assert asked == [(k * STEP, (k + 1) * STEP) for k in range(first_new, n)]
    torch.testing.assert_close(filt.t, ref.t, rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.q, ref.q, rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.cov, ref.cov, rtol=1e-9, atol=1e-15)
    # a second late pose replays over the new twists, not the old ones
    second = _meas(1)
    assert line.add(40 * STEP, "pose", second)
    ref2 = PoseUKF(1, dtype=torch.float64)
    ref2.update(*pose)
    ref2.predict(old[12], (first_new * STEP - t_pose) * 1e-6)
    for k in range(first_new, n):
        ref2.predict(new[k], STEP * 1e-6)
        if (k + 1) * STEP == 40 * STEP:
            ref2.update(*second)
    torch.testing.assert_close(filt.t, ref2.t, rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.q, ref2.q, rtol=0, atol=1e-12)


def test_remeasure_keeps_a_twist_when_asked_for_none_and_checks_its_input() -> None:
    n = 20
    twists = _twists(n)
    filt = PoseUKF(1, dtype=torch.float64)
    _start(filt)
    line = PoseTimeline(filt, horizon_us=10_000)
    for k in range(n):
        line.step((k + 1) * STEP, twists[k])
    before = (filt.t.clone(), filt.q.clone())
    assert line.remeasure(12_000, lambda a, b: None) == 8
    torch.testing.assert_close(filt.t, before[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(filt.q, before[1], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="outside the kept past"):
        line.remeasure(5_000, lambda a, b: None)  # older than the 10 ms kept
    with pytest.raises(ValueError, match="twist-driven"):
        PoseTimeline(PoseTwistUKF(1), 10_000).remeasure(0, lambda a, b: None)


@pytest.mark.parametrize("make", FILTERS)
@pytest.mark.parametrize("kinds", [("pose",), ("pose", "range", "aligned")])
def test_batched_replay_equals_step_by_step_replay_bit_for_bit(kinds, make) -> None:
    """The measurement-free runs of a replay go through one ``PoseUKF.predict_run`` call
    each: every kept snapshot (probed by ``pose_at``) and the final state equal the replay
    step by step exactly, counters included."""
    n = 120
    twists = _twists(n)
    lines = []
    for batched in (True, False):
        filt = make()
        _start(filt)
        line = PoseTimeline(filt, horizon_us=50_000)
        line.batch_replay = batched
        for k in range(n):
            line.step((k + 1) * STEP, twists[k])
            if k % 20 == 19:  # a measurement 15.5 ms in the past, of each kind in turn
                tm = (k + 1) * STEP - 15_500
                kind = kinds[(k // 20) % len(kinds)]
                t, q = _meas(k)
                if kind == "range":
                    line.add(tm, "range", (torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64),
                                           t[:, 2]), torch.tensor([1e-4], dtype=torch.float64))
                else:
                    line.add(tm, kind, (t, q), torch.eye(6, dtype=torch.float64)[None] * 1e-3)
        lines.append(line)
    fast, slow = lines
    for name in fast.names:
        assert torch.equal(getattr(fast.filter, name), getattr(slow.filter, name)), name
    for t_us in range(fast._times[0], fast.now + 1, 250):
        a, b = fast.pose_at(t_us), slow.pose_at(t_us)
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]), t_us
    for snap_a, snap_b in zip(fast._snaps, slow._snaps, strict=True):
        for x, y in zip(snap_a, snap_b, strict=True):
            assert torch.equal(x, y)


@pytest.mark.parametrize("make", FILTERS)
def test_predict_run_equals_predict_calls_and_declines_batches(make) -> None:
    twists = _twists(7)
    dts = [1e-3, 2.5e-4, 1e-3, 3e-3, 1e-6, 1e-3, 7e-4]
    run, ref = make(), make()
    _start(run)
    _start(ref)
    if make is _biased:
        for filt in (run, ref):
            filt.bias = torch.tensor([[0.05, -0.02, 0.3]], dtype=torch.float64)
    states = run.predict_run(list(twists), dts)
    assert states is not None
    for k in range(len(dts)):
        ref.predict(twists[k], dts[k])
        assert torch.equal(states[0][k], ref.t) and torch.equal(states[1][k], ref.q)
        assert torch.equal(states[2][k], ref.cov)
    assert torch.equal(run.t, ref.t) and torch.equal(run.cov, ref.cov)
    if make is _biased:
        assert run.cov.shape == (1, 9, 9) and torch.equal(run.bias, ref.bias)
    # not the compiled single-track path: None, nothing changed
    two = PoseUKF(2, dtype=torch.float64)
    before = two.t.clone()
    assert two.predict_run([torch.zeros(2, 6, dtype=torch.float64)], [1e-3]) is None
    assert torch.equal(two.t, before)
    single = PoseUKF(1, dtype=torch.float32)
    assert single.predict_run([torch.zeros(1, 6)], [1e-3]) is None
    with pytest.raises(ValueError, match="2 twists but 1 time steps"):
        run.predict_run(list(twists[:2]), [1e-3])


@pytest.mark.parametrize("make", FILTERS)
def test_step_run_equals_steps_bit_for_bit_and_late_poses_replay_the_same(make) -> None:
    """``step_run`` (one compiled predict for a run of steps) keeps the same times, twists and
    snapshots as ``step`` per step, so a late pose then replays to the same state; the past
    beyond the horizon is trimmed the same."""
    n = 90
    twists = _twists(n)
    lines = []
    for runs in (True, False):
        filt = make()
        _start(filt)
        line = PoseTimeline(filt, horizon_us=40_000)
        k = 0
        for size in [1, 10, 3, 7, 10, 10, 2, 10, 10, 10, 10, 7]:  # uneven runs, 90 steps
            ends = [(j + 1) * STEP + 250 * (j % 3 == 1) for j in range(k, k + size)]
            if runs and size > 1:
                assert line.step_run(ends, twists[k:k + size]) is not None
            else:
                for j, t_end in enumerate(ends):
                    line.step(t_end, twists[k + j])
            k += size
        assert k == n
        cov = torch.eye(6, dtype=torch.float64)[None] * 1e-3
        line.add(n * STEP - 23_400, "pose", _meas(3), cov)
        lines.append(line)
    fast, slow = lines
    assert list(fast._times) == list(slow._times)
    for name in fast.names:
        assert torch.equal(getattr(fast.filter, name), getattr(slow.filter, name)), name
    for a, b in zip(fast._twists, slow._twists, strict=True):
        assert (a is None and b is None) or torch.equal(a, b)
    for snap_a, snap_b in zip(fast._snaps, slow._snaps, strict=True):
        for x, y in zip(snap_a, snap_b, strict=True):
            assert torch.equal(x, y)


def test_step_run_declines_where_not_compiled_and_checks_its_times() -> None:
    twists = _twists(3)
    line = PoseTimeline(PoseTwistUKF(1, dtype=torch.float64), 10_000)
    assert line.step_run([1000, 2000, 3000], twists) is None  # constant-velocity filter
    single = PoseUKF(1, dtype=torch.float32)
    _start(single)
    line = PoseTimeline(single, 10_000)
    assert line.step_run([1000, 2000, 3000], twists.float()) is None
    assert line.now == 0 and len(line._snaps) == 1
    filt = PoseUKF(1, dtype=torch.float64)
    _start(filt)
    line = PoseTimeline(filt, 10_000)
    with pytest.raises(ValueError, match="must rise"):
        line.step_run([1000, 1000, 3000], twists)
    with pytest.raises(ValueError, match="must rise"):
        line.step_run([0, 1000, 2000], twists)
    with pytest.raises(ValueError, match="3 times but 2 twists"):
        line.step_run([1000, 2000, 3000], twists[:2])


def test_step_ends_are_the_kept_step_ends_in_a_half_open_span() -> None:
    """``step_ends(a, b)``: the kept step ends in (a, b], the ones trimmed off the kept past
    (5 ms horizon) no longer among them."""
    filt = PoseUKF(1)
    _start(filt)
    line = PoseTimeline(filt, horizon_us=5_000)
    for k in range(20):
        line.step((k + 1) * STEP, torch.zeros(1, 6, dtype=torch.float64))
    assert line.step_ends(17 * STEP, 19 * STEP) == [18 * STEP, 19 * STEP]
    assert line.step_ends(17 * STEP + 1, 19 * STEP - 1) == [18 * STEP]
    assert line.step_ends(line.now, line.now + STEP) == []
    kept = line.step_ends(-1, line.now)
    assert kept[-1] == line.now and kept[0] >= line.now - 5_000 - STEP and len(kept) < 20
