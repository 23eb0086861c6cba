"""Which rotations the frame alignments observed (:mod:`evtrack.tracking.observability`): the
marginal rotational information against a brute-force inverse, the object frame, the rule
over sources; and on simulated frames, a cylinder's spin unseen by depth but seen by its
texture."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from tracker_helpers import TEST_TRACKER, make_tracker, sim_config

from evtrack import Sequence
from evtrack.filters.lie import pivot_map
from evtrack.sim.engine import simulate
from evtrack.sim.objects import procedural_object
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.observability import RotationObservability, rotational_information
from evtrack.tracking.tracker import Tracker


def _spd(rng: np.random.Generator, weights) -> np.ndarray:
    Q = Rotation.random(random_state=rng).as_matrix()
    A = np.zeros((6, 6))
    A[:3, :3] = Q
    A[3:, 3:] = Rotation.random(random_state=rng).as_matrix()
    M = rng.normal(size=(6, 6)) * 0.1 + A
    return M @ np.diag(weights) @ M.T


@pytest.mark.parametrize("seed", range(5))
def test_rotational_information_is_the_inverse_of_the_marginal_covariance(seed) -> None:
    rng = np.random.default_rng(seed)
    info = _spd(rng, rng.uniform(0.5, 50.0, 6))
    brute = np.linalg.inv(np.linalg.inv(info)[3:, 3:])
    np.testing.assert_allclose(rotational_information(info), brute, rtol=1e-9, atol=1e-9)


def test_rotational_information_does_not_depend_on_the_pivot() -> None:
    """``[δv, δω]`` about a point ``c`` is ``M [δt, δθ]`` about the origin; the rotation's
    marginal is the same."""
    rng = np.random.default_rng(7)
    info = _spd(rng, rng.uniform(0.5, 50.0, 6))
    M = pivot_map(torch.tensor([0.05, -0.2, 0.3], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(rotational_information(M.T @ info @ M),
                               rotational_information(info), rtol=1e-9, atol=1e-9)


def test_an_unseen_translation_does_not_break_it() -> None:
    info = np.diag([1.0, 1.0, 0.0, 4.0, 9.0, 16.0])
    np.testing.assert_allclose(rotational_information(info), np.diag([4.0, 9.0, 16.0]))
    with pytest.raises(ValueError, match=r"\(6, 6\)"):
        rotational_information(np.eye(5))
    with pytest.raises(ValueError, match="finite"):
        rotational_information(np.full((6, 6), np.nan))


def test_the_axis_is_reported_in_the_object_frame() -> None:
    """A fit that did not see a turn about the camera's z sees the object's axis ``Rᵀ z``;
    one alignment's standard deviation is ``1 / sqrt(information)`` there."""
    R = Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix()
    info = np.diag([1e4, 1e4, 1e4, 1e6, 1e6, 100.0])
    obs = RotationObservability()
    obs.add("depth", info, variance=4.0, rotation=R)
    obs.add("depth", info, variance=4.0, rotation=R)
    (found,) = obs.unobserved(max_std_deg=2.0)
    expected = R.T @ [0.0, 0.0, 1.0]
    assert abs(float(found.axis @ expected)) > 1 - 1e-9
    assert found.std_deg["depth"] == pytest.approx(np.degrees(1 / np.sqrt(100.0 / 4.0)))
    assert obs.alignments == {"depth": 2}
    assert obs.unobserved(max_std_deg=20.0) == []


def test_an_axis_is_unobserved_only_when_every_source_left_it() -> None:
    sees_x = np.diag([1.0, 1.0, 1.0, 1e6, 1.0, 1.0])
    sees_y = np.diag([1.0, 1.0, 1.0, 1.0, 1e6, 1.0])
    obs = RotationObservability()
    obs.add("depth", sees_x, 1.0, np.eye(3))
    assert sorted(np.abs(u.axis).round(6).tolist() for u in obs.unobserved()) == [
        [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]
    obs.add("appearance", sees_y, 1.0, np.eye(3))
    (found,) = obs.unobserved()
    assert found.axis.round(6).tolist() == [0.0, 0.0, 1.0]
    assert found.std_deg == pytest.approx({"depth": np.degrees(1.0),
                                           "appearance": np.degrees(1.0)})
    obs.add("appearance", np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 1e6]), 1.0, np.eye(3))
    assert obs.unobserved() == []  # the mean of its two alignments sees z
    assert RotationObservability().unobserved() == []  # nothing measured, nothing said
    with pytest.raises(ValueError, match="max_std_deg"):
        obs.unobserved(0.0)
    with pytest.raises(ValueError, match="non-finite"):
        obs.add("depth", np.eye(6), float("inf"), np.eye(3))


@pytest.fixture(scope="module")
def can_sequence(tmp_path_factory) -> Sequence:
    """A textured procedural cylinder (axis: the object's y) moving fast, 0.6 s at 256x192
    (at 128x96 it covers too few pixels for the appearance alignment)."""
    out = tmp_path_factory.mktemp("observability") / "can"
    cfg = sim_config(0.6, 4)
    simulate(procedural_object("can", 0), dataclasses.replace(
        cfg, camera=cfg.camera.resized(256, 192)), out)
    return Sequence.load(out)


def test_depth_alone_cannot_see_a_cylinder_spin(can_sequence) -> None:
    """Depth alignments of a plain cylinder leave its spin about its axis unobserved (one
    alignment's ±4.8° at 640x480, ±3.8° here); its texture pins it."""
    tracker, _ = make_tracker(can_sequence, depth_fusion={"icp": True})
    trajectory = tracker.track(can_sequence)
    assert tracker.stats.depth_alignments >= 8
    (found,) = tracker.unobserved_rotations()
    assert abs(float(found.axis[1])) > 0.98, found
    assert set(found.std_deg) == {"depth"} and found.std_deg["depth"] > 2.0
    assert trajectory.meta["rotations"]["unobserved"][0]["axis"][1] == pytest.approx(
        float(found.axis[1]), abs=1e-4)

    t0 = int(can_sequence.ground_truth.pose_t_us[0])
    model = Tracker.for_sequence(can_sequence, TrackerConfig.from_dict(
        {**TEST_TRACKER, "pose_source": "model"}))
    model.track(can_sequence, start_pose=can_sequence.ground_truth.pose_at(t0), start_t_us=t0)
    assert model.stats.appearance_alignments >= 3 and model.stats.depth_alignments >= 8
    assert model.unobserved_rotations() == []
    assert model.observability.std_deg("appearance", [0.0, 1.0, 0.0]) < 2.0
    assert model.observability.std_deg("depth", [0.0, 1.0, 0.0]) > 2.0


def test_a_box_has_every_rotation_observed(fast_sequence) -> None:
    """The depth alignments of the procedural box see every rotation."""
    tracker, _ = make_tracker(fast_sequence, depth_fusion={"icp": True})
    tracker.track(fast_sequence)
    assert tracker.stats.depth_alignments >= 8
    assert tracker.unobserved_rotations() == []
    for axis in np.eye(3):
        assert tracker.observability.std_deg("depth", axis) < 1.0


def test_the_track_command_names_the_unobserved_axis(can_sequence, fast_sequence, tmp_path,
                                                     capsys) -> None:
    from evtrack.cli import main

    out = tmp_path / "pose.csv"
    assert main(["track", str(can_sequence.root), "--out", str(out), "--oracle", "--quiet",
                 "--depth-icp"]) == 0
    text = capsys.readouterr().out
    assert re.search(r"the frame alignments did not observe the rotation about the object's "
                     r"axis \(\+0\.0\d, \+(1\.00|0\.99), \+0\.0\d\): depth ±", text), text
    assert "from the events and the pose source only" in text
    assert main(["track", str(fast_sequence.root), "--out", str(out), "--oracle", "--quiet",
                 "--depth-icp"]) == 0
    assert "did not observe" not in capsys.readouterr().out


def test_the_docstring_example_runs() -> None:
    import doctest

    from evtrack.tracking import observability

    result = doctest.testmod(observability)
    assert result.attempted >= 3 and result.failed == 0
