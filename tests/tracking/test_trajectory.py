"""Trajectory files: round trips, atomic writes, errors on malformed files."""

from __future__ import annotations

import pytest
import torch
from scipy.spatial.transform import Rotation

from evtrack.errors import EventFileError
from evtrack.tracking.trajectory import Trajectory


def _traj(n: int = 50) -> Trajectory:
    g = torch.Generator().manual_seed(0)
    R = torch.from_numpy(Rotation.random(n, random_state=1).as_matrix())
    T = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T[:, :3, :3] = R
    T[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=torch.float64)
    T[3] = float("nan")
    status = torch.ones(n, dtype=torch.int8)
    status[3] = 0
    return Trajectory(torch.arange(n) * 1000 + 7, T, torch.randn(n, 6, generator=g,
                                                                 dtype=torch.float64),
                      status, "full", {"note": "x", "values": [1, 2]})


@pytest.mark.parametrize("suffix", [".csv", ".h5"])
def test_round_trip(tmp_path, suffix) -> None:
    a = _traj()
    path = tmp_path / f"t{suffix}"
    a.save(path)
    b = Trajectory.load(path)
    assert torch.equal(a.t_us, b.t_us) and torch.equal(a.status, b.status)
    assert b.method == "full" and b.meta == a.meta
    atol = 1e-8 if suffix == ".csv" else 0.0
    torch.testing.assert_close(b.poses, a.poses, rtol=0, atol=atol, equal_nan=True)
    torch.testing.assert_close(b.twists, a.twists, rtol=0, atol=atol)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary left


def test_failed_save_leaves_nothing(tmp_path) -> None:
    bad = _traj()
    bad.meta = {"obj": object()}
    path = tmp_path / "t.csv"
    with pytest.raises(TypeError):
        bad.save(path)
    assert list(tmp_path.iterdir()) == []


def test_malformed_files(tmp_path) -> None:
    good = tmp_path / "g.csv"
    _traj().save(good)
    lines = good.read_text().splitlines()
    cut = tmp_path / "cut.csv"
    cut.write_text("\n".join(lines[:10] + [lines[10][:20]]) + "\n")
    with pytest.raises(EventFileError, match="line 11.*truncated"):
        Trajectory.load(cut)
    nohead = tmp_path / "nohead.csv"
    nohead.write_text("1,2,3\n")
    with pytest.raises(EventFileError, match="header"):
        Trajectory.load(nohead)
    with pytest.raises(EventFileError, match="not found"):
        Trajectory.load(tmp_path / "missing.csv")
    other = tmp_path / "x.h5"
    import h5py

    with h5py.File(other, "w") as f:
        f["t_us"] = [1]
    with pytest.raises(EventFileError, match="not an evtrack trajectory"):
        Trajectory.load(other)
    with pytest.raises(ValueError, match="format"):
        _traj().save(tmp_path / "t.txt")


def test_times_must_increase() -> None:
    with pytest.raises(ValueError, match="increasing"):
        Trajectory(torch.tensor([1, 1]), torch.eye(4).repeat(2, 1, 1), torch.zeros(2, 6),
                   torch.ones(2))


def test_field_shapes_and_the_method_name_are_checked() -> None:
    with pytest.raises(ValueError, match=r"poses must be \(2, 4, 4\) for 2 timestamps"):
        Trajectory(torch.tensor([1, 2]), torch.eye(4).repeat(3, 1, 1), torch.zeros(2, 6),
                   torch.ones(2))
    with pytest.raises(ValueError, match=r"twists must be \(2, 6\)"):
        Trajectory(torch.tensor([1, 2]), torch.eye(4).repeat(2, 1, 1), torch.zeros(2, 7),
                   torch.ones(2))
    with pytest.raises(ValueError, match="one-line string"):  # its CSV header would not load
        Trajectory(torch.tensor([1, 2]), torch.eye(4).repeat(2, 1, 1), torch.zeros(2, 6),
                   torch.ones(2), method="full\nsecond line")
