"""Depth refinement (point-to-plane ICP on a registered depth frame), pinned by the simulator's
exact depth and its ground-truth poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.models import PoseDetection
from evtrack.models.depth_refine import DepthRefineConfig, DepthRefiner
from evtrack.sim.objects import make_box
from evtrack.sim.renderer import Renderer
from evtrack.sim.scene import background_plane
from evtrack.sim.trajectory import rotvec_to_matrix

CAM = PinholeCamera(300.0, 300.0, 159.5, 119.5, 320, 240)
K = CAM.K().numpy()
BOX = make_box(seed=0)


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(np.asarray(rotvec, float))
    T[:3, 3] = t
    return T


def _render_depth(pose: np.ndarray, background_at: float | None = None) -> np.ndarray:
    with Renderer(CAM) as r:
        if background_at is not None:
            part = background_plane(CAM, background_at, np.full((4, 4, 3), 128, np.uint8), 0.5)
            r.add_static(part.mesh, part.pose)
        r.set_object(BOX)
        depth = r.render(pose).depth.copy()
    depth[depth <= 0] = np.nan
    return depth


def _errors(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    dt = float(np.linalg.norm(T[:3, 3] - truth[:3, 3]))
    cos = np.clip((np.trace(T[:3, :3] @ truth[:3, :3].T) - 1) / 2, -1, 1)
    return dt, math.degrees(math.acos(cos))


def _perturb(T: np.ndarray, dt, rotvec) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = rotvec_to_matrix(np.asarray(rotvec, float)) @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + np.asarray(dt)
    return out


REFINER = DepthRefiner(BOX.vertices, BOX.faces)
VIEWS = [  # three faces in view, at several distances and turns
    _pose([0.5, -0.6, 0.2], [0.02, -0.01, 0.55]),
    _pose([-0.7, 0.4, 1.0], [-0.05, 0.03, 0.8]),
    _pose([2.4, 0.3, -0.5], [0.0, 0.02, 1.0]),
]


@pytest.mark.parametrize("truth", VIEWS)
def test_recovers_the_simulated_pose_from_a_network_like_error(truth) -> None:
    depth = _render_depth(truth)
    # the error of a keypoint network: mostly along the ray, with a tilt
    start = _perturb(truth, [0.02, -0.015, 0.09], [0.12, -0.1, 0.08])
    assert _errors(start, truth)[0] > 0.08 and _errors(start, truth)[1] > 9
    res = REFINER.refine(start, depth, K)
    assert res.refined and res.refusal == "", res.reason
    dt, dr = _errors(res.pose, truth)
    assert dt < 1e-3 and dr < 0.2, (dt, dr)
    assert res.inliers >= 0.8 * res.visible and res.rmse_m < 1e-3


def test_noise_dropout_and_a_wall_behind() -> None:
    truth = VIEWS[1]
    depth = _render_depth(truth, background_at=1.1)
    rng = np.random.default_rng(0)
    depth = depth + rng.standard_normal(depth.shape) * 0.0024 * depth ** 2  # RealSense-like
    depth[rng.random(depth.shape) < 0.1] = np.nan
    start = _perturb(truth, [-0.01, 0.02, -0.06], [-0.1, 0.05, 0.1])
    res = REFINER.refine(start, depth.astype(np.float32), K)
    assert res.refined, res.reason
    dt, dr = _errors(res.pose, truth)
    assert dt < 3e-3 and dr < 1.0, (dt, dr)


def test_a_flat_face_seen_head_on_keeps_what_the_depth_cannot_tell() -> None:
    """Only the front face is in view: depth fixes the distance and the tilt, not the slide
    within the face nor the turn about its normal, which stay at the start's values."""
    truth = _pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.7])
    depth = _render_depth(truth)
    start = _perturb(truth, [0.01, 0.0, 0.05], [0.0, 0.0, math.radians(4)])
    res = REFINER.refine(start, depth, K)
    assert res.refined, res.reason
    assert abs(res.pose[2, 3] - truth[2, 3]) < 1e-3  # the distance is measured
    assert abs(res.pose[0, 3] - start[0, 3]) < 2e-3  # the slide is not
    turn = math.degrees(math.atan2(res.pose[1, 0], res.pose[0, 0]))
    assert abs(turn - 4.0) < 0.5


def test_refuses_without_usable_depth() -> None:
    truth = VIEWS[0]
    start = _perturb(truth, [0.0, 0.0, 0.03], [0.0, 0.0, 0.0])
    holes = np.full((CAM.height, CAM.width), np.nan, np.float32)
    res = REFINER.refine(start, holes, K)
    assert not res.refined and "depth pixels" in res.reason
    assert res.refusal == "few depth pixels" and res.information is None
    np.testing.assert_array_equal(res.pose, start)
    wall = np.full((CAM.height, CAM.width), 2.5, np.float32)  # the object is not there
    res = REFINER.refine(start, wall, K)
    assert not res.refined and res.reason
    assert res.refusal in ("few depth pixels", "few fit")
    np.testing.assert_array_equal(res.pose, start)
    with pytest.raises(ValueError, match="metres"):
        REFINER.refine(start, np.zeros((CAM.height, CAM.width), np.uint16), K)
    bad = start.copy()
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        REFINER.refine(bad, holes, K)


def test_refuses_an_implausibly_large_correction() -> None:
    truth = VIEWS[0]
    depth = _render_depth(truth)
    start = _perturb(truth, [0.0, 0.0, 0.0], [0.0, 0.15, 0.0])  # 8.6 degrees off
    assert REFINER.refine(start, depth, K).refined
    tight = DepthRefiner(BOX.vertices, BOX.faces, DepthRefineConfig(max_rotation_deg=5.0))
    res = tight.refine(start, depth, K)
    assert not res.refined and "max_rotation_deg" in res.reason
    assert res.refusal == "correction too large"
    np.testing.assert_array_equal(res.pose, start)


def test_refine_detections_replaces_only_refined_poses() -> None:
    truth = VIEWS[0]
    depth = _render_depth(truth)
    good = _perturb(truth, [0.0, 0.01, 0.05], [0.05, 0.0, 0.0])
    lost = _pose([0, 0, 0], [5.0, 0.0, 1.0])  # projects outside the image
    dets = [PoseDetection(torch.as_tensor(p), 0.9, torch.zeros(9, 2), torch.ones(9), 1.0, 9,
                          "box") for p in (good, lost)]
    out = REFINER.refine_detections(dets, depth, K)
    assert _errors(out[0].pose.numpy(), truth)[0] < 1e-3
    torch.testing.assert_close(out[1].pose, dets[1].pose)
    assert out[0].confidence == 0.9 and out[0].object_name == "box"


@pytest.mark.parametrize("field", ["gate_m", "iterations", "min_points", "max_translation_m"])
def test_config_is_checked(field) -> None:
    with pytest.raises(ConfigError, match=field):
        DepthRefineConfig(**{field: 0})
    with pytest.raises(ConfigError, match="final_gate_m"):
        DepthRefineConfig(gate_m=0.01, final_gate_m=0.02)
