"""npz reader: foreign conventions it accepts, and the errors it raises."""

from __future__ import annotations

import numpy as np
import pytest

from evtrack.errors import EventFileError
from evtrack.io import open_events, read_events


def _save(path, **arrays):
    np.savez(path, **arrays)
    return path


def _arrays(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return dict(x=rng.integers(0, 64, n), y=rng.integers(0, 48, n),
                t=np.sort(rng.integers(0, 10_000, n)), p=rng.choice([-1, 1], n),
                sensor_size=np.array([64, 48]))


def test_foreign_npz_with_unsigned_or_bool_polarity(tmp_path):
    a = _arrays()
    ref = read_events(_save(tmp_path / "pm.npz", **a))
    assert ref.sensor_size == (64, 48)
    unsigned = (a["p"] > 0).astype(np.uint8)
    assert read_events(_save(tmp_path / "u.npz", **{**a, "p": unsigned})) == ref
    assert read_events(_save(tmp_path / "b.npz", **{**a, "p": a["p"] > 0})) == ref
    no_size = {k: v for k, v in a.items() if k != "sensor_size"}
    assert read_events(_save(tmp_path / "n.npz", **no_size)).sensor_size is None


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a: a.pop("p"), r"missing array\(s\) \['p'\]"),
        (lambda a: a.update(y=a["y"][:-1]), "different lengths"),
        (lambda a: a.update(t=a["t"].astype(float)), "'t' must be 1-D integers"),
        (lambda a: a.update(x=a["x"].reshape(5, 10)), "'x' must be 1-D integers"),
        (lambda a: a.update(p=np.where(np.arange(50) == 4, 3, a["p"])),
         r"1 events with polarity other than ±1 \(or 0/1\), first at index 4 \(p=3\)"),
        (lambda a: a.update(p=np.where(np.arange(50) == 9, 0, a["p"])), "mixes 0/1 and ±1"),
        (lambda a: a.update(sensor_size=np.array([64])), "'sensor_size' must hold two"),
        (lambda a: a.update(t=a["t"][::-1].copy()), "timestamps go backwards"),
        (lambda a: a.update(x=a["x"] + 64), "outside the sensor"),
        (lambda a: a.update(x=a["x"].astype(np.int64) + 2**40), "does not fit int32"),
    ],
)
def test_bad_npz(tmp_path, change, message):
    a = _arrays()
    change(a)
    path = _save(tmp_path / "bad.npz", **a)
    with pytest.raises(EventFileError, match=message) as info:
        read_events(path)
    assert "bad.npz" in str(info.value)


def test_a_foreign_npz_is_named_briefly(tmp_path):
    """An archive of many other arrays (a torch .pt is one) is refused in one short line."""
    path = _save(tmp_path / "many.npz", **{f"w{i}": np.zeros(1) for i in range(200)})
    with pytest.raises(EventFileError, match=r"and 194 more\): not an event") as info:
        read_events(path)
    assert len(str(info.value)) < 300


def test_truncated_and_flipped_npz(tmp_path):
    path = _save(tmp_path / "g.npz", **_arrays(500))
    data = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) - 100])
    with pytest.raises(EventFileError, match="cut.npz"):
        read_events(tmp_path / "cut.npz")
    flipped = bytearray(data)
    pos = data.find(b"t.npy") + 200  # inside the t member's data
    flipped[pos] ^= 0x01
    (tmp_path / "flip.npz").write_bytes(bytes(flipped))
    with pytest.raises(EventFileError, match="flip.npz"):  # CRC-32 of the member
        read_events(tmp_path / "flip.npz")


def test_metadata_without_loading(tmp_path):
    path = _save(tmp_path / "m.npz", **_arrays(70))
    with open_events(path) as r:
        assert r.num_events == 70 and r.sensor_size == (64, 48)
        assert r._arrays is None  # shapes came from the .npy headers
