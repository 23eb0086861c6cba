"""Native HDF5: layout, the ms index, time-window reads, and corrupt-file errors."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from evtrack.errors import EventFileError
from evtrack.events import Events, concatenate
from evtrack.io import EventWriter, Hdf5Reader, open_events, read_events, write_events


def _brute_ms_table(t: np.ndarray, t0: int) -> np.ndarray:
    """ms_to_idx by definition, with a Python loop (independent of the writer's searchsorted)."""
    out = []
    k = 0
    while True:
        bound = t0 + 1000 * k
        idx = next((i for i, v in enumerate(t.tolist()) if v >= bound), len(t))
        out.append(idx)
        if idx == len(t):
            return np.array(out)
        k += 1


def test_layout_matches_the_documented_one(tmp_path, events_factory):
    ev = events_factory(4000, seed=1, mean_dt=3)  # ~12 ms
    path = tmp_path / "l.h5"
    with EventWriter(path, ev.sensor_size, chunk_events=256) as w:
        for part in ev.windows(count=501):  # table built across chunk boundaries
            w.write(part)
    with h5py.File(path, "r") as f:
        assert f["events/x"].dtype == np.int16 and f["events/y"].dtype == np.int16
        assert f["events/t"].dtype == np.int64 and f["events/p"].dtype == np.int8
        assert f["events/t"].chunks == (256,)
        assert (f.attrs["sensor_width"], f.attrs["sensor_height"]) == (640, 480)
        assert f.attrs["t0_us"] == ev.t_start and f.attrs["num_events"] == len(ev)
        assert f.attrs["format_version"] == 1
        table = f["ms_to_idx"][()]
        assert np.array_equal(f["events/t"][()], ev.t.numpy())
    assert np.array_equal(table, _brute_ms_table(ev.t.numpy(), ev.t_start))


def test_explicit_t0_and_wide_sensor(tmp_path, events_factory):
    ev = events_factory(500, seed=2, sensor_size=(40_000, 100), coord_dtype=np.int32)
    path = tmp_path / "w.h5"
    with EventWriter(path, ev.sensor_size, t0_us=0) as w:
        w.write(ev)
    with h5py.File(path, "r") as f:
        assert f["events/x"].dtype == np.int32
        assert f.attrs["t0_us"] == 0
        assert np.array_equal(f["ms_to_idx"][()], _brute_ms_table(ev.t.numpy(), 0))
    assert read_events(path) == ev
    with pytest.raises(Exception, match="after the first event"), \
            EventWriter(tmp_path / "x.h5", ev.sensor_size, t0_us=ev.t_start + 1) as w:
        w.write(ev)
    assert not (tmp_path / "x.h5").exists()


def test_time_window_reads_equal_between(tmp_path, events_factory):
    ev = events_factory(6000, seed=3, mean_dt=5)
    path = tmp_path / "r.h5"
    write_events(path, ev, chunk_events=512)
    rng = np.random.default_rng(0)
    t_lo, t_hi = ev.t_start, ev.t_end
    windows = [(t_lo, t_hi + 1), (t_lo - 5000, t_lo), (t_hi + 1, t_hi + 9000), (t_lo, t_lo),
               (t_lo - 1, t_lo + 1), (t_hi, t_hi + 1), (t_lo + 1000, t_lo + 2000)]
    windows += [tuple(sorted(rng.integers(t_lo - 100, t_hi + 100, 2).tolist()))
                for _ in range(40)]
    with open_events(path) as r:
        assert r.indexed and r.num_events == len(ev)
        assert (r.t_start, r.t_end) == (ev.t_start, ev.t_end)
        for a, b in windows:
            assert r.read(a, b) == ev.between(a, b), (a, b)
        assert r.read(None, t_lo + 3000) == ev.between(t_lo - 1, t_lo + 3000)
        assert r.read(t_lo + 3000, None) == ev.between(t_lo + 3000, t_hi + 1)


def test_window_reads_without_ms_table_use_bisection(tmp_path, events_factory):
    ev = events_factory(3000, seed=4)
    path = tmp_path / "n.h5"
    write_events(path, ev)
    with h5py.File(path, "a") as f:
        del f["ms_to_idx"]
    with Hdf5Reader(path, block_events=64) as r:
        for a, b in [(ev.t_start + 100, ev.t_start + 5000), (0, ev.t_start + 7)]:
            assert r.read(a, b) == ev.between(a, b)
    assert read_events(path) == ev


def test_streaming_windows_match_events_windows(tmp_path, events_factory):
    ev = events_factory(5000, seed=5)
    path = tmp_path / "s.h5"
    write_events(path, ev)
    with Hdf5Reader(path, block_events=333) as r:
        for d in (1, 250, 1000, 10**9):
            got = list(r.iter_windows(d))
            want = list(ev.windows(d))
            assert len(got) == len(want) and all(g == w for g, w in zip(got, want, strict=True))
        got = list(r.iter_windows(300, include_empty=True, t_start_us=ev.t_start - 1000))
        want = list(ev.windows(300, include_empty=True, t_start_us=ev.t_start - 1000))
        assert [len(g) for g in got] == [len(w) for w in want]
        assert concatenate(got) == ev


# ----------------------------------------------------------------------------- bad files
def _good(tmp_path, events_factory, n=500):
    path = tmp_path / "g.h5"
    write_events(path, events_factory(n, seed=6), chunk_events=128)
    return path


def test_missing_dataset(tmp_path, events_factory):
    path = _good(tmp_path, events_factory)
    with h5py.File(path, "a") as f:
        del f["events/p"]
    with pytest.raises(EventFileError, match="g.h5: missing dataset 'events/p'"):
        read_events(path)


def test_datasets_of_different_lengths(tmp_path, events_factory):
    path = _good(tmp_path, events_factory)
    with h5py.File(path, "a") as f:
        f["events/y"].resize((400,))
    with pytest.raises(EventFileError, match=r"different lengths \(x=500, y=400, t=500, p=500\)"):
        read_events(path)


def test_count_attribute_mismatch(tmp_path, events_factory):
    path = _good(tmp_path, events_factory)
    with h5py.File(path, "a") as f:
        f.attrs["num_events"] = 501
    with pytest.raises(EventFileError, match="num_events=501 but the datasets hold 500"):
        read_events(path)


def test_corrupt_ms_table(tmp_path, events_factory):
    path = _good(tmp_path, events_factory)
    with h5py.File(path, "a") as f:
        table = f["ms_to_idx"][()]
        f["ms_to_idx"][2] = table[2] + 1
        t = f["events/t"][()]
        t0 = int(f.attrs["t0_us"])
    with pytest.raises(EventFileError, match="'ms_to_idx' disagrees with events/t"):
        read_events(path)
    with open_events(path) as r, pytest.raises(EventFileError, match="not the window"):
        r.read(t0 + 2000, t0 + 2500)
    assert len(t) == 500
    with h5py.File(path, "a") as f:
        del f["ms_to_idx"]
        f["ms_to_idx"] = np.zeros(3, dtype=np.int64)
    with pytest.raises(EventFileError, match="'ms_to_idx' has 3 entries"):
        open_events(path)


@pytest.mark.parametrize(
    ("field", "values", "message"),
    [
        ("t", lambda t: np.concatenate([t[:100], t[100:110][::-1], t[110:]]),
         r"timestamps go backwards, first at index 10[0-9]"),
        ("x", lambda x: np.where(np.arange(len(x)) % 50 == 7, 700, x),
         r"10 events outside the sensor \(640, 480\), first at index 7 \(x=700"),
        ("p", lambda p: np.where(np.arange(len(p)) == 33, 0, p),
         r"1 events with polarity other than ±1, first at index 33 \(p=0\)"),
    ],
)
def test_invalid_events_in_file(tmp_path, events_factory, field, values, message):
    path = _good(tmp_path, events_factory)
    with h5py.File(path, "a") as f:
        f[f"events/{field}"][...] = values(f[f"events/{field}"][()])
        del f["ms_to_idx"]  # keep the index out of the way: the events themselves are bad
    with pytest.raises(EventFileError, match=message) as info:
        read_events(path)
    assert "g.h5" in str(info.value)
    with pytest.raises(EventFileError, match="invalid events"):
        list(Hdf5Reader(path, block_events=64).iter_chunks())


def test_checksum_catches_flipped_data_bytes(tmp_path):
    ev = Events(np.full(1000, 5), np.full(1000, 6), np.arange(1000), np.ones(1000), (640, 480))
    path = tmp_path / "c.h5"
    write_events(path, ev)
    data = bytearray(path.read_bytes())
    # x is stored as int16 5s: find a run of them and change one value (still in the sensor)
    pos = data.find(np.full(64, 5, dtype=np.int16).tobytes())
    assert pos > 0
    data[pos] = 7
    path.write_bytes(bytes(data))
    with pytest.raises(EventFileError, match="Fletcher32|checksum|cannot read"):
        read_events(path)


def test_not_an_event_file(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["data"] = np.arange(3)
    with pytest.raises(EventFileError, match="missing group 'events'"):
        read_events(path)
    with h5py.File(path, "w") as f:
        f["events/x"] = np.zeros((2, 2))
    with pytest.raises(EventFileError, match="missing dataset|1-D integer"):
        read_events(path)


def test_truncated_file(tmp_path, events_factory):
    path = _good(tmp_path, events_factory, n=3000)
    data = path.read_bytes()
    (tmp_path / "cut.h5").write_bytes(data[: len(data) // 2])
    with pytest.raises(EventFileError, match="cut.h5"):
        read_events(tmp_path / "cut.h5")


def test_newer_format_version_is_refused(tmp_path, events_factory):
    path = _good(tmp_path, events_factory)
    with h5py.File(path, "a") as f:
        f.attrs["format_version"] = 2
    with pytest.raises(EventFileError, match="format_version 2 is newer"):
        read_events(path)
