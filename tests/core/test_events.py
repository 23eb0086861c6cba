"""Tests of the Events container."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evtrack import Events, EventsError, concatenate


def make_events(n: int = 100, seed: int = 0, size=(64, 48)) -> Events:
    g = np.random.default_rng(seed)
    t = np.sort(g.integers(0, 1_000_000, n))
    return Events(g.integers(0, size[0], n), g.integers(0, size[1], n), t,
                  g.choice([-1, 1], n), sensor_size=size)


def test_dtypes_and_len():
    ev = make_events(10)
    assert len(ev) == 10
    assert ev.t.dtype == torch.int64 and ev.p.dtype == torch.int8
    assert ev.x.dtype == torch.int32 and ev.y.dtype == torch.int32
    ev16 = Events(torch.tensor([1], dtype=torch.int16), torch.tensor([2], dtype=torch.int16),
                  [5], [1])
    assert ev16.x.dtype == torch.int16


def test_large_timestamps_are_exact():
    t = [10**15 + 1, 10**15 + 2]
    ev = Events([0, 0], [0, 0], t, [1, 1])
    assert ev.t.tolist() == t


def test_mismatched_lengths_raise():
    with pytest.raises(EventsError, match="differ in length"):
        Events([1, 2], [1], [1, 2], [1, 1])


def test_fractional_coordinates_raise():
    with pytest.raises(EventsError, match="integers"):
        Events(np.array([1.5]), [1], [1], [1])


@pytest.mark.parametrize(("fields", "match"), [
    (([1, 2], [3, 4], [10, 20], np.array([1, 255], np.uint8)), r"Events.p holds 255"),
    (([1, 2], [3, 4], [10, 20], [257, -1]), r"Events.p holds 257"),
    ((np.array([2**32 + 5, 2], np.int64), [3, 4], [10, 20], [1, -1]), "Events.x holds 4294967301"),
    ((np.array([1, 2], np.int16), np.array([3, 40000], np.int32), [10, 20], [1, -1]),
     r"Events.y holds 40000, outside the torch.int16 range"),
    (([1.0, 2.0], [3, 4], [1e30, 2.0], [1, 1]), "Events.t holds 1e"),
    ((np.array([True, False]), [1, 2], [1, 2], [1, 1]), "dtype torch.bool"),
])
def test_values_that_would_wrap_around_in_the_stored_dtype_raise(fields, match):
    with pytest.raises(EventsError, match=match):
        Events(*fields)


def test_values_of_a_narrower_dtype_are_stored_without_a_check():
    ev = Events(np.array([639], np.uint16), np.array([479], np.uint16),
                np.array([7], np.int32), np.array([-1], np.int8))
    assert ev.x.dtype == torch.int32 and int(ev.x[0]) == 639 and int(ev.t[0]) == 7


@pytest.mark.parametrize("size", [(640, 480, 3), (640.7, 480), ("a", 3), 5, (0, 480)])
def test_sensor_size_must_be_two_positive_whole_numbers(size):
    with pytest.raises(EventsError, match="sensor_size must be"):
        Events([1], [1], [1], [1], sensor_size=size)
    assert Events([1], [1], [1], [1], sensor_size=(640.0, 480)).sensor_size == (640, 480)


def test_slicing_and_masks():
    ev = make_events(50)
    assert ev[3:7] == Events(ev.x[3:7], ev.y[3:7], ev.t[3:7], ev.p[3:7], ev.sensor_size)
    assert len(ev[ev.p > 0]) == int((ev.p > 0).sum())
    one = ev[4]
    assert len(one) == 1 and int(one.t[0]) == int(ev.t[4])
    assert int(ev[-1].t[0]) == ev.t_end


def test_masks_and_index_tensors_select_as_torch_indexing():
    """Boolean masks and index tensors (torch or NumPy; CPU events take NumPy's gather) give
    the events torch's indexing gives, in order, with the same dtypes; bad indices raise."""
    ev = make_events(300, seed=5)
    g = np.random.default_rng(6)
    mask = torch.from_numpy(g.random(300) < 0.4)
    index = torch.from_numpy(g.integers(-300, 300, 120))
    for sel in (mask, index, mask.numpy(), index.numpy(), torch.zeros(300, dtype=torch.bool),
                torch.zeros(0, dtype=torch.int64)):
        got = ev[sel]
        want = torch.as_tensor(sel)
        for k in ("x", "y", "t", "p"):
            ref = getattr(ev, k)[want]
            assert torch.equal(getattr(got, k), ref) and getattr(got, k).dtype == ref.dtype
        assert got.sensor_size == ev.sensor_size
    with pytest.raises(IndexError):
        ev[torch.ones(299, dtype=torch.bool)]
    with pytest.raises(IndexError):
        ev[torch.tensor([0, 300])]


@pytest.mark.parametrize("coord_dtype", [torch.int16, torch.int32])
def test_mask_compaction_matches_numpy_at_the_edges(coord_dtype):
    """The compiled one-pass compaction of CPU masks gives NumPy's boolean indexing of each
    field, also for all-true, all-false, first-only and last-only masks."""
    g = np.random.default_rng(11)
    n = 1000
    ev = Events(torch.from_numpy(g.integers(0, 640, n)).to(coord_dtype),
                torch.from_numpy(g.integers(0, 480, n)).to(coord_dtype),
                np.sort(g.integers(0, 10**6, n)), g.choice([-1, 1], n), sensor_size=(640, 480))
    first, last = np.zeros(n, bool), np.zeros(n, bool)
    first[0], last[-1] = True, True
    for mask in (g.random(n) < 0.5, np.ones(n, bool), np.zeros(n, bool), first, last):
        got = ev[torch.from_numpy(mask)]
        for k in ("x", "y", "t", "p"):
            want = getattr(ev, k).numpy()[mask]
            assert np.array_equal(getattr(got, k).numpy(), want)
            assert getattr(got, k).dtype == getattr(ev, k).dtype


def test_between_matches_brute_force():
    ev = make_events(500, seed=1)
    for t0, t1 in [(0, 10), (100_000, 300_000), (999_999, 2_000_000), (5, 5)]:
        got = ev.between(t0, t1)
        mask = (ev.t >= t0) & (ev.t < t1)
        assert got == ev[mask]


def test_time_windows_partition_the_events():
    ev = make_events(1000, seed=2)
    windows = list(ev.windows(duration_us=50_000))
    assert concatenate(windows) == ev
    t0 = ev.t_start
    for w in windows:
        k = (int(w.t[0]) - t0) // 50_000
        assert bool(((w.t - t0) // 50_000 == k).all())


def test_count_windows():
    ev = make_events(1001, seed=3)
    windows = list(ev.windows(count=100))
    assert [len(w) for w in windows] == [100] * 10 + [1]
    assert concatenate(windows) == ev


def test_windows_include_empty():
    ev = Events([0, 0], [0, 0], [0, 1000], [1, 1])
    assert len(list(ev.windows(duration_us=100))) == 2
    assert len(list(ev.windows(duration_us=100, include_empty=True))) == 11


def test_windows_argument_errors():
    ev = make_events(5)
    with pytest.raises(ValueError):
        list(ev.windows())
    with pytest.raises(ValueError):
        list(ev.windows(duration_us=0))


def test_empty_events():
    ev = Events.empty((10, 10))
    assert len(ev) == 0 and ev.validate().ok
    assert list(ev.windows(duration_us=10)) == []
    assert len(ev.between(0, 10)) == 0
    with pytest.raises(EventsError):
        _ = ev.t_start


def test_validate_reports_counts_and_first_index():
    ev = Events([1, 2, 70, 3, 80], [1, 1, 1, -1, 1], [10, 5, 20, 30, 25], [1, 0, 1, -1, 2],
                sensor_size=(64, 48))
    rep = ev.validate()
    assert not rep.ok
    assert (rep.unsorted, rep.first_unsorted) == (2, 1)
    assert (rep.outside, rep.first_outside) == (3, 2)
    assert (rep.bad_polarity, rep.first_bad_polarity) == (2, 1)
    with pytest.raises(EventsError, match="my.file"):
        ev.check("my.file")


@pytest.mark.parametrize("sensor", [(64, 48), None])
def test_compiled_problem_count_equals_the_report(sensor):
    """The one-pass count that lets ``validate`` return early on good events agrees with the
    report's NumPy counts and first indices, on events with every kind of problem."""
    from evtrack.events import _count_problems

    g = np.random.default_rng(7)
    for trial in range(30):
        n = int(g.integers(1, 400))
        x = g.integers(-3, 70, n).astype(np.int16)
        y = g.integers(-3, 52, n).astype(np.int16)
        t = np.sort(g.integers(0, 10_000, n))
        if trial % 3 == 0:  # some go backwards
            t[g.integers(0, n, max(1, n // 20))] -= 50
        p = g.choice([-1, 1, 0, 2] if trial % 2 else [-1, 1], n).astype(np.int8)
        if trial % 5 == 0:  # all good
            x, y = np.clip(x, 0, 47), np.clip(y, 0, 47)
        ev = Events(x, y, t, p, sensor_size=sensor)
        rep = ev.validate()
        w, h = sensor if sensor is not None else (-1, -1)
        assert _count_problems(x, y, t, p, w, h) == (
            rep.unsorted, rep.first_unsorted, rep.outside, rep.first_outside,
            rep.bad_polarity, rep.first_bad_polarity), trial


def test_validate_against_a_given_sensor_size():
    """``validate(sensor_size)`` checks the coordinates against that size instead of the
    events' own (or their unknown one), in the compiled count and in the report."""
    ev = Events([1, 40, 10], [1, 2, 30], [1, 2, 3], [1, -1, 1], sensor_size=(64, 48))
    assert ev.validate().ok
    rep = ev.validate((32, 24))
    assert (rep.outside, rep.first_outside) == (2, 1) and "(32, 24)" in str(rep)
    unknown = Events([1, 40, 10], [1, 2, 30], [1, 2, 3], [1, -1, 1])
    assert unknown.validate().ok and unknown.validate((32, 24)).outside == 2
    assert ev.validate((64, 48)) == ev.validate()


def test_validate_ok():
    assert make_events(100).validate().ok


def test_unsigned_polarity():
    ev = Events.from_unsigned_polarity([1, 2], [1, 2], [1, 2], [0, 1])
    assert ev.p.tolist() == [-1, 1]
    with pytest.raises(EventsError):
        Events.from_unsigned_polarity([1], [1], [1], [2])


def test_from_structured():
    arr = np.zeros(3, dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])
    arr["t"], arr["x"], arr["p"] = [1, 2, 3], [4, 5, 6], [0, 1, 1]
    ev = Events.from_structured(arr, (10, 10))
    assert ev.p.tolist() == [-1, 1, 1] and ev.x.tolist() == [4, 5, 6]
    with pytest.raises(EventsError, match="lacks fields"):
        Events.from_structured(np.zeros(2, dtype=[("t", "<i8")]))


def test_concatenate_checks_sensor_size():
    a = make_events(5, size=(10, 10))
    b = make_events(5, size=(20, 20))
    with pytest.raises(EventsError, match="sensor sizes"):
        concatenate([a, b])
    c = concatenate([a, Events([1], [1], [10**7], [1])])
    assert len(c) == 6 and c.sensor_size == (10, 10)


def test_to_device_roundtrip(device):
    ev = make_events(20)
    moved = ev.to(device)
    assert moved.device.type == device.type
    assert moved.to("cpu") == ev

