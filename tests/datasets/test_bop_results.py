"""BOP results CSV: its exact text, the round trip, and a trajectory sampled at image times."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from bop_scene import pose

from evtrack.datasets.bop_results import (
    BOP_RESULTS_HEADER,
    BopResult,
    bop_record,
    read_bop_results,
    sequence_bop_rows,
    trajectory_bop_rows,
    write_bop_results,
)
from evtrack.errors import ConfigError, EventFileError
from evtrack.geometry import integrate_twist
from evtrack.sequence import SequenceMeta
from evtrack.tracking.trajectory import STATUS_LOST, STATUS_TRACKING, STATUS_WAITING, Trajectory

T_A = pose([0.3, -0.2, 0.1], [0.05, -0.02, 0.6])
T_B = pose([-1.0, 0.4, 2.0], [-0.1234567, 0.03, 0.9])


def test_results_text_format(tmp_path: Path) -> None:
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [0.0125, -0.5, 1.25]
    path = tmp_path / "res.csv"
    write_bop_results(path, [BopResult(48, 7, 5, 0.5, T), BopResult(48, 9, 5, 1.0, T, 0.25)])
    assert path.read_text() == (
        "scene_id,im_id,obj_id,score,R,t,time\n"
        "48,7,5,0.5,0.0 -1.0 0.0 1.0 0.0 0.0 0.0 0.0 1.0,12.5 -500.0 1250.0,-1\n"
        "48,9,5,1.0,0.0 -1.0 0.0 1.0 0.0 0.0 0.0 0.0 1.0,12.5 -500.0 1250.0,0.25\n")


def test_results_round_trip(tmp_path: Path) -> None:
    rows = [BopResult(1, 0, 3, 0.9, T_A, 0.01), BopResult(1, 4, 3, 0.25, T_B)]
    path = tmp_path / "out" / "method_ycbv-test.csv"
    write_bop_results(path, rows)
    back = read_bop_results(path)
    assert [(r.scene_id, r.im_id, r.obj_id, r.score, r.time_s) for r in back] == [
        (1, 0, 3, 0.9, 0.01), (1, 4, 3, 0.25, -1.0)]
    for a, b in zip(rows, back, strict=True):
        np.testing.assert_allclose(b.T_m2c, a.T_m2c, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back[1].t_mm, T_B[:3, 3] * 1000.0, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(back[1].R, T_B[:3, :3])  # shortest round-trip text: exact
    assert not [p for p in path.parent.iterdir() if p.name != path.name]  # no temporary left


@pytest.mark.parametrize(("text", "message"), [
    ("scene,im,obj\n", "line 1: expected the header scene_id,im_id,obj_id,score,R,t,time"),
    (f"{BOP_RESULTS_HEADER}\n1,2,3,1.0,1 0 0 0 1 0 0 0 1,0 0 1\n", "line 2: expected 7"),
    (f"{BOP_RESULTS_HEADER}\n1,2,3,1.0,1 0 0 0 1 0 0 0,0 0 1,-1\n",
     "line 2: field 'R' must hold 9 number(s), got 8"),
    (f"{BOP_RESULTS_HEADER}\n1,2,3,1.0,1 0 0 0 1 0 0 0 1,0 x 1,-1\n",
     "line 2: field 't' must hold numbers"),
    (f"{BOP_RESULTS_HEADER}\n1,a,3,1.0,1 0 0 0 1 0 0 0 1,0 0 1,-1\n",
     "line 2: scene_id, im_id and obj_id must be integers"),
    ("", "no header line"),
])
def test_bad_results_files(tmp_path: Path, text, message) -> None:
    path = tmp_path / "r.csv"
    path.write_text(text)
    with pytest.raises(EventFileError) as info:
        read_bop_results(path)
    assert str(info.value).startswith(f"{path}: {message}")


def test_a_non_finite_pose_is_not_written(tmp_path: Path) -> None:
    T = T_A.copy()
    T[0, 3] = np.nan
    with pytest.raises(ValueError, match="scene 1, image 2, object 3: T_m2c must be a finite"):
        write_bop_results(tmp_path / "r.csv", [BopResult(1, 2, 3, 1.0, T)])
    assert not (tmp_path / "r.csv").exists()


# ---------------------------------------------------------------------------- trajectories
def _trajectory(status: list[int]) -> tuple[Trajectory, torch.Tensor]:
    """Samples every 1 ms from 10 ms, moving with a constant twist from T_A."""
    n = len(status)
    t = 10_000 + 1000 * torch.arange(n)
    V = torch.tensor([0.2, -0.1, 0.3, 1.0, -2.0, 0.5], dtype=torch.float64)
    poses = integrate_twist(torch.from_numpy(T_A).expand(n, 4, 4), V.expand(n, 6),
                            (t - 10_000) * 1e-6)
    poses = poses.clone()
    poses[torch.tensor(status) == STATUS_WAITING] = float("nan")
    return Trajectory(t, poses, V.expand(n, 6), torch.tensor(status)), V


def test_trajectory_rows_at_image_times() -> None:
    status = [STATUS_WAITING] * 3 + [STATUS_TRACKING] * 10 + [STATUS_LOST] * 3 + [
        STATUS_TRACKING] * 4
    traj, V = _trajectory(status)
    times = [9_000, 12_500, 13_000, 16_400, 23_999, 26_000, 28_700, 29_000, 29_001]
    ids = [0, 1, 2, 3, 4, 5, 6, 7, 8]
    rows = trajectory_bop_rows(traj, times, ids, scene_id=3, obj_id=7, score=0.75)
    # before the trajectory, waiting, lost and after it: no row
    assert [r.im_id for r in rows] == [2, 3, 5, 6, 7]
    assert {(r.scene_id, r.obj_id, r.score, r.time_s) for r in rows} == {(3, 7, 0.75, -1.0)}
    for r in rows:
        t_s = (times[r.im_id] - 10_000) * 1e-6  # between samples: moved on by the twist
        expected = integrate_twist(torch.from_numpy(T_A), V, t_s).numpy()
        np.testing.assert_allclose(r.T_m2c, expected, rtol=0, atol=1e-8)


def test_trajectory_rows_in_another_frame() -> None:
    traj, V = _trajectory([STATUS_TRACKING] * 5)
    T_frame_event = pose([0.0, 0.2, -0.1], [0.05, 0.0, -0.01])
    rows = trajectory_bop_rows(traj, [12_000], [4], 1, 2, T_frame_event=T_frame_event)
    event = integrate_twist(torch.from_numpy(T_A), V, 0.002).numpy()
    np.testing.assert_allclose(rows[0].T_m2c, T_frame_event @ event, rtol=0, atol=1e-9)
    # a point of the object seen from the other camera: P_f = T_fe (T_e P_o)
    P_o = np.array([0.01, 0.02, -0.03, 1.0])
    np.testing.assert_allclose(rows[0].T_m2c @ P_o, T_frame_event @ (event @ P_o), atol=1e-12)
    with pytest.raises(ValueError, match="2 image times but 1 image ids"):
        trajectory_bop_rows(traj, [1, 2], [4], 1, 2)


def _meta(extra: dict, T_event_rgb: np.ndarray | None = None) -> SequenceMeta:
    from evtrack import PinholeCamera

    cam = PinholeCamera(100.0, 100.0, 31.5, 23.5, 64, 48)
    return SequenceMeta(event_camera=cam, name="s", rgb_camera=cam, extra=extra,
                        T_event_rgb=np.eye(4) if T_event_rgb is None else T_event_rgb)


def test_sequence_rows_take_the_ground_truth_camera() -> None:
    traj, _ = _trajectory([STATUS_TRACKING] * 5)
    T_event_rgb = pose([0.1, 0.0, 0.0], [-0.06, 0.0, 0.0])
    record = {"scene_id": 2, "obj_id": 5, "im_ids": [10, 11], "im_times_us": [11_000, 13_000]}
    rgb = sequence_bop_rows(traj, _meta({"bop": {**record, "gt_frame": "rgb"}}, T_event_rgb))
    event = sequence_bop_rows(traj, _meta({"bop": {**record, "gt_frame": "event"}}, T_event_rgb))
    assert [r.im_id for r in rgb] == [10, 11] and rgb[0].scene_id == 2 and rgb[0].obj_id == 5
    for a, b in zip(rgb, event, strict=True):
        np.testing.assert_allclose(a.T_m2c, np.linalg.inv(T_event_rgb) @ b.T_m2c, atol=1e-12)


@pytest.mark.parametrize(("extra", "message"), [
    ({}, "meta.yaml extra.bop is missing"),
    ({"bop": {"scene_id": 1, "obj_id": 2, "im_ids": [1], "gt_frame": "rgb"}},
     "missing field 'im_times_us'"),
    ({"bop": {"scene_id": 1, "obj_id": 2, "im_ids": [1], "im_times_us": [5],
              "gt_frame": "depth"}}, "gt_frame must be 'rgb' or 'event'"),
    ({"bop": {"scene_id": 1, "obj_id": 2, "im_ids": [1], "im_times_us": [],
              "gt_frame": "rgb"}}, "im_ids and im_times_us must be lists of one length"),
])
def test_sequences_without_a_bop_record(extra, message) -> None:
    with pytest.raises(ConfigError, match=message):
        bop_record(_meta(extra))
