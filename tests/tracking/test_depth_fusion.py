"""The mesh aligned with depth frames (``depth_icp``): its covariance in the pose filter's
tangent, and its use in the tracker."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tracker_helpers import make_tracker

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.eval.metrics import rotation_errors
from evtrack.models.depth_refine import RefineResult
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.depth_fusion import alignment_covariance
from evtrack.tracking.tracker import Tracker


def _residuals(delta: np.ndarray, P: np.ndarray, normals: np.ndarray, t: np.ndarray
               ) -> np.ndarray:
    """Point-to-plane residuals of the object's points ``P`` (camera frame) moved by the pose
    filter's perturbation ``δ = [δt, δθ]``: ``P → exp(δθ)(P − t) + t + δt``."""
    moved = Rotation.from_rotvec(delta[3:]).apply(P - t) + t + delta[:3]
    return ((moved - P) * normals).sum(1)


@pytest.mark.parametrize("seed", [0, 1])
def test_alignment_covariance_against_a_finite_difference_fit(seed) -> None:
    """The fit's covariance carried into the filter's tangent against the least-squares
    covariance ``σ² (JᵀJ)⁻¹`` with ``J`` the finite-difference Jacobian of the residuals in the
    filter's own perturbation (about the object's origin, not the fit's centre)."""
    rng = np.random.default_rng(seed)
    t = np.array([0.05, -0.03, 0.8])
    centre = t + rng.normal(0, 0.03, 3)  # the mesh's box centre is not its origin
    P = centre + rng.normal(0, 0.05, (300, 3))
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    a = np.hstack([normals, np.cross(P - centre, normals)])
    pose = np.eye(4)
    pose[:3, 3] = t
    res = RefineResult(pose, True, 300, 300, 0.002, 5, "", a.T @ a, centre)
    J = np.zeros((300, 6))
    h = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        J[:, k] = (_residuals(d, P, normals, t) - _residuals(-d, P, normals, t)) / (2 * h)
    expected = 0.002 ** 2 * np.linalg.inv(J.T @ J)
    floors = np.diag([1e-6] * 3 + [1e-4] * 3)
    got = alignment_covariance(res, 1e-3, 1e-2)
    np.testing.assert_allclose(got - floors, expected, rtol=1e-5, atol=1e-14)


def test_unseen_direction_gets_a_huge_variance() -> None:
    """Points on a cylinder about z (a can seen by the depth): turning about its axis moves
    nothing along the normals, so that variance is orders above the others."""
    ang = np.linspace(0, np.pi, 200)
    P = np.stack([0.04 * np.cos(ang), 0.04 * np.sin(ang) - 0.1, np.linspace(-.05, .05, 200)],
                 1) + [0, 0, 0.8]
    normals = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
    centre = np.array([0, -0.1, 0.8])
    a = np.hstack([normals, np.cross(P - centre, normals)])
    pose = np.eye(4)
    pose[:3, 3] = centre
    cov = alignment_covariance(RefineResult(pose, True, 200, 200, 0.001, 3, "", a.T @ a,
                                             centre), 0.0, 0.0)
    assert cov[5, 5] > 1e4 * max(cov[3, 3], cov[4, 4])
    assert np.isfinite(cov).all()


def test_a_barely_seen_direction_counts_as_unseen() -> None:
    """A can with a little ridge (one row of normals tilted round the axis): the fit sees its
    spin, but at ~0.3 % of its best direction's information (per metre of surface motion).
    With ``min_share`` 0.01 that direction gets the unseen variance; below the share it keeps
    the fit's own; the well-seen directions keep theirs, and nothing becomes surer."""
    ang = np.linspace(0, np.pi, 400)
    P = np.stack([0.04 * np.cos(ang), 0.04 * np.sin(ang) - 0.1, np.linspace(-.05, .05, 400)],
                 1) + [0, 0, 0.8]
    normals = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
    ridge = np.arange(0, 400, 40)  # tilted round the axis: these see the spin
    tangent = np.stack([-np.sin(ang), np.cos(ang), np.zeros_like(ang)], 1)
    normals[ridge] = 0.8 * normals[ridge] + 0.6 * tangent[ridge]
    centre = np.array([0, -0.1, 0.8])
    a = np.hstack([normals, np.cross(P - centre, normals)])
    pose = np.eye(4)
    pose[:3, 3] = centre
    res = RefineResult(pose, True, 400, 400, 0.001, 3, "", a.T @ a, centre)
    kept = alignment_covariance(res, 0.0, 0.0, radius_m=0.06, min_share=0.0)
    cut = alignment_covariance(res, 0.0, 0.0, radius_m=0.06, min_share=0.01)
    assert np.degrees(np.sqrt(kept[5, 5])) < 1.0  # the fit claims to see the spin
    assert cut[5, 5] > 1e4 * kept[5, 5]
    assert np.linalg.eigvalsh(cut - kept).min() > -1e-12 * np.abs(kept).max()
    scale = np.r_[np.ones(3), np.full(3, 0.06)]  # the pose's origin is the fit's centre here
    w, V = np.linalg.eigh(a.T @ a / np.outer(scale, scale))
    for k in np.nonzero(w > 0.2 * w.max())[0]:  # well seen: the same variance
        v = V[:, k] * scale
        assert abs(v @ cut @ v - v @ kept @ v) <= 1e-6 * (v @ kept @ v)
    lower = alignment_covariance(res, 0.0, 0.0, radius_m=0.06, min_share=1e-4)
    np.testing.assert_allclose(lower, kept, rtol=1e-9)


def _rotation_rmse_deg(traj, seq, t_from_us: int) -> float:
    gt = seq.ground_truth
    t = traj.t_us.numpy()
    keep = (t >= t_from_us) & np.isfinite(traj.poses.numpy()[:, 0, 0])
    est = traj.poses[keep]
    err = rotation_errors(est, gt.pose_at(traj.t_us[keep]).reshape(-1, 4, 4))
    return float(np.degrees(np.sqrt((err.numpy() ** 2).mean())))


def test_tracker_aligns_depth_frames_and_tracks_rotation_better(fast_sequence) -> None:
    """Oracle poses with 2 cm / 0.1 rad noise: the full method's rotation error with the
    depth alignment (every depth frame) is well below that without. Measured after 150 ms:
    17.6 deg without, 0.86 with (1.46 at the default 30 Hz); 30 of the 36 depth frames
    aligned (those before the first pose, 100 ms late, find no track). Bounds: 0.5x, and 60 %
    of the frames."""
    seq = fast_sequence
    oracle = {"std_translation": 0.02, "std_rotation": 0.1}
    plain, _ = make_tracker(seq, oracle=oracle)
    aligned, _ = make_tracker(seq, oracle=oracle, depth_fusion={"icp": True, "icp_rate_hz": 100.0})
    a, b = plain.track(seq), aligned.track(seq)
    assert plain.stats.depth_alignments == 0 and plain.depth_fusion is None
    st = aligned.stats
    frames = len(seq.depth_times_us)
    assert st.depth_alignments >= 0.6 * frames, st.depth_alignments_skipped
    assert set(st.depth_alignments_skipped) <= {"few depth pixels", "few fit",
                                                 "correction too large"}
    e_plain, e_aligned = _rotation_rmse_deg(a, seq, 150_000), _rotation_rmse_deg(b, seq,
                                                                                 150_000)
    assert e_aligned < 0.5 * e_plain, (e_plain, e_aligned)


def test_alignment_rate_is_bounded(fast_sequence) -> None:
    seq = fast_sequence
    tracker, _ = make_tracker(seq, depth_fusion={"icp": True, "icp_rate_hz": 10.0})
    tracker.track(seq)
    st = tracker.stats
    tried = st.depth_alignments + sum(st.depth_alignments_skipped.values())
    duration_s = float(seq.depth_times_us[-1] - seq.depth_times_us[0]) * 1e-6
    assert 1 <= tried <= duration_s * 10.0 + 1


def test_depth_icp_config_is_checked(fast_sequence) -> None:
    with pytest.raises(ConfigError, match="depth.source 'sensor'"):
        TrackerConfig.from_dict({"depth_fusion": {"icp": True}, "depth": {"source": "model"}})
    for name in ("icp_rate_hz", "icp_std_m", "icp_points"):
        with pytest.raises(ConfigError, match=f"depth_fusion.{name}"):
            TrackerConfig.from_dict({"depth_fusion": {name: 0}})
    cube = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])
    with pytest.raises(ConfigError, match="mesh"):
        Tracker(TrackerConfig(depth_fusion={"icp": True}), camera=PinholeCamera(160.0, 160.0, 63.5,
                                                                                47.5,
                                                                    128, 96), mesh=cube)
    velocity, _ = make_tracker(fast_sequence, method="velocity", depth_fusion={"icp": True})
    assert velocity.depth_fusion is None


@pytest.mark.parametrize("method", ["pose", "frame-flow", "ge"])
def test_every_pose_filter_method_aligns_depth_frames(fast_sequence, method) -> None:
    """The baselines with a pose filter align depth frames too (frame-flow's depth is in the
    RGB camera: the aligned pose and its covariance are carried into the event camera's
    frame); every frame tried is fused or refused with a reason, and the track stays finite.
    Measured on an AMD EPYC (2026-11-27): pose 12 fused of 15 tried, frame-flow 15 of 15,
    ge 4 of 15 (its track errs more: 5 refused as "few fit", 5 as "correction too large");
    ge fused 5 on other machines. Bounds: 3 fused of at least 10 tried."""
    seq = fast_sequence
    tracker, _ = make_tracker(seq, method=method, depth_fusion={"icp": True})
    traj = tracker.track(seq)
    st = tracker.stats
    assert set(st.depth_alignments_skipped) <= {"few depth pixels", "few fit",
                                                 "correction too large"}
    assert st.depth_alignments >= 3
    assert st.depth_alignments + sum(st.depth_alignments_skipped.values()) >= 10
    assert np.isfinite(traj.poses.numpy()[traj.status.numpy() > 0]).all()
