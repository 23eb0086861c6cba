"""The tracker's outputs (evtrack.tracking.outputs): samples, the lookup of a past sample,
the trajectory, and the view check that loses the object."""

from __future__ import annotations

import numpy as np
import torch
from tracker_helpers import SMALL_CAM, rigid_pose

from evtrack.geometry import matrix_to_tq
from evtrack.tracking.outputs import TrackOutputs, ViewCheck, extrapolated, quat_to_matrix
from evtrack.tracking.silhouette import Silhouette
from evtrack.tracking.trajectory import STATUS_LOST, STATUS_TRACKING, STATUS_WAITING

CUBE = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])


def _tq(T: np.ndarray) -> np.ndarray:
    t, q = matrix_to_tq(torch.from_numpy(T))
    return np.concatenate([t.numpy(), q.numpy()])


def test_quat_to_matrix_inverts_matrix_to_tq() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        T = rigid_pose(rng.normal(size=3), rng.normal(size=3))
        tq = _tq(T)
        np.testing.assert_allclose(quat_to_matrix(tq[:3], tq[3:]), T, atol=1e-12)


def test_samples_and_the_lookup_of_a_past_one() -> None:
    out = TrackOutputs()
    out.append(1000, np.full(7, np.nan), np.zeros(6), STATUS_WAITING)
    poses = [rigid_pose([0, 0, 0.1 * i], [0, 0, 0.5]) for i in range(3)]
    twists = np.arange(18.0).reshape(3, 6)
    out.extend_tracking([2000, 3000, 4000], np.stack([_tq(T) for T in poses]), twists)
    assert len(out) == 4 and out.status == [STATUS_WAITING] + [STATUS_TRACKING] * 3
    twist, T, t_ref = out.sample_before(3500)
    assert t_ref == 3000 and np.array_equal(twist, twists[1])
    np.testing.assert_allclose(T, poses[1], atol=1e-12)
    assert np.isnan(out.sample_before(1500)[1]).all()  # waiting: no pose
    assert out.sample_before(500)[2] == 500  # before any sample
    traj = out.trajectory("full", {"x": 1})
    assert traj.t_us.tolist() == [1000, 2000, 3000, 4000] and traj.method == "full"
    assert torch.isnan(traj.poses[0]).all()
    np.testing.assert_allclose(traj.poses[3].numpy(), poses[2], atol=1e-12)


def test_extrapolated_moves_the_pose_by_the_twist() -> None:
    T = rigid_pose([0, 0, 0], [0, 0, 0.5])
    twist = np.array([0.1, 0, 0, 0, 0, 0])
    assert extrapolated(twist, T, 1000, None) is T
    moved = extrapolated(twist, T, 1000, 11_000)
    np.testing.assert_allclose(moved[:3, 3], [0.001, 0, 0.5], atol=1e-12)
    nan = np.full((4, 4), np.nan)
    assert extrapolated(twist, nan, 0, 5000) is nan


def test_the_view_check_loses_the_object_after_enough_steps_out_of_view() -> None:
    view = ViewCheck(Silhouette(CUBE, SMALL_CAM), min_visible_fraction=0.5, lost_after_ms=3.0,
                     step_us=1000)
    inside = _tq(rigid_pose([0, 0, 0], [0, 0, 0.5]))
    outside = _tq(rigid_pose([0, 0, 0], [5.0, 0, 0.5]))
    assert view.in_view(inside[:3], inside[3:])
    assert view.in_view(outside[:3], outside[3:]) and view.in_view(outside[:3], outside[3:])
    assert not view.in_view(outside[:3], outside[3:])  # the third step out: lost
    assert view.in_view(inside[:3], inside[3:]) and view.out_of_view_us == 0
    assert STATUS_LOST != STATUS_TRACKING
