"""The object's range on depth frames (evtrack.tracking.depth_range) and its use in the tracker."""

from __future__ import annotations

import numpy as np
import pytest
from tracker_helpers import make_tracker

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.sim.objects import procedural_object
from evtrack.sim.renderer import Renderer
from evtrack.tracking.config import TrackerConfig
from evtrack.tracking.depth_range import DepthRange
from evtrack.tracking.tracker import Tracker

CAM = PinholeCamera(160.0, 160.0, 63.5, 47.5, 128, 96)


def _pose(t: tuple[float, float, float], angle: float = 0.4) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]] @ np.array([[1, 0, 0], [0, c, -s],
                                                                [0, s, c]])
    T[:3, 3] = t
    return T


@pytest.fixture(scope="module")
def scene():
    """A box, its true pose, and the depth frame a perfect sensor takes of it (NaN off it)."""
    box = procedural_object("box", 0)
    truth = _pose((0.03, -0.02, 0.6))
    with Renderer(CAM) as r:
        r.set_object(box)
        z = r.render_raw(truth)[..., 3].copy()
    depth = np.where(z > 0, z, np.nan).astype(np.float32)
    rng = np.random.default_rng(0)
    noisy = depth + rng.normal(0, 0.002, depth.shape).astype(np.float32)
    ranger = DepthRange(box, CAM, std_m=0.005)
    return box, truth, depth, noisy, ranger


@pytest.mark.parametrize("shift", [-0.04, -0.01, 0.02, 0.05])
def test_range_recovers_the_position_along_the_ray(scene, shift) -> None:
    """The predicted pose is the true one moved along its viewing ray (and a little across
    it, and turned): the measured ``uᵀ t`` is the true one within 2 mm, with 2 mm sensor
    noise per pixel."""
    _, truth, _, noisy, ranger = scene
    u = truth[:3, 3] / np.linalg.norm(truth[:3, 3])
    pred = _pose(tuple(truth[:3, 3] + shift * u + np.array([0.003, 0.002, 0.0])), angle=0.43)
    res = ranger.measure(noisy, pred)
    assert res.ok, res.detail
    np.testing.assert_allclose(res.direction, pred[:3, 3] / np.linalg.norm(pred[:3, 3]))
    assert abs(res.distance - float(res.direction @ truth[:3, 3])) < 0.002
    assert ranger.std_m ** 2 <= res.variance < (ranger.std_m ** 2) * 1.05
    assert res.inliers > 0.9 * res.cells >= 100


def test_range_refuses_frames_it_cannot_trust(scene) -> None:
    _, truth, depth, _, ranger = scene
    u = truth[:3, 3] / np.linalg.norm(truth[:3, 3])
    off = ranger.measure(depth, _pose(tuple(truth[:3, 3] + 0.15 * u)))
    assert off.reason == "offset too large" and not np.isfinite(off.distance)
    beside = ranger.measure(depth, _pose((0.5, 0.0, 0.6)))  # out of the image
    assert beside.reason == "too few cells" and beside.cells == 0
    missing = ranger.measure(np.full_like(depth, np.nan), truth)
    assert missing.reason == "too few cells"
    # depths scattered over +-10 cm (a broken frame): no majority near the median offset
    rng = np.random.default_rng(1)
    scattered = depth + rng.uniform(-0.1, 0.1, depth.shape).astype(np.float32)
    assert ranger.measure(scattered, truth).reason == "too few agreeing"
    behind = _pose((0.0, 0.0, -0.5))
    assert ranger.measure(depth, behind).reason == "no pose"


def test_range_ignores_a_partial_occluder(scene) -> None:
    """40 % of the object's pixels behind a nearer occluder: the median offset and its inliers
    are the object's, and the range is as accurate as without the occluder."""
    _, truth, depth, _, ranger = scene
    cols = np.flatnonzero(np.isfinite(depth).any(0))
    occluded = depth.copy()
    covered = cols[: int(0.4 * len(cols))]
    occluded[:, covered] = 0.45
    res = ranger.measure(occluded, truth)
    assert res.ok, res.detail
    assert abs(res.distance - float(np.linalg.norm(truth[:3, 3]))) < 0.001
    assert res.inliers < 0.75 * res.cells


def _depth_rmse_cm(traj, seq, t_from_us: int) -> float:
    """RMSE of the position error along the true viewing ray (cm), after ``t_from_us``."""
    gt = seq.ground_truth
    t = traj.t_us.numpy()
    keep = (t >= t_from_us) & np.isfinite(traj.poses.numpy()[:, 0, 0])
    k = np.clip(np.searchsorted(gt.pose_t_us.numpy(), t[keep]), 0, len(gt.pose_t_us) - 1)
    true_t = gt.poses.numpy()[k, :3, 3]
    u = true_t / np.linalg.norm(true_t, axis=1, keepdims=True)
    err = ((traj.poses.numpy()[keep, :3, 3] - true_t) * u).sum(1)
    return float(100 * np.sqrt(np.mean(err ** 2)))


def test_tracker_fuses_ranges_and_tracks_depth_better(fast_sequence) -> None:
    """Oracle poses with 2 cm noise at 10 Hz: the depth error of the full method with the range
    of every depth frame is well below that without. Measured after 150 ms: 4.27 cm without,
    1.55 cm with; 28 of the 36 depth frames fused (those before the first pose, which arrives
    100 ms late, find no track). Since the tracker's flow reports RoI windows of 2
    supporting events (``flow.min_support``, 2026-11-26) the run without ranges is better:
    2.95 cm without, 1.78 cm with. On an AMD EPYC (2026-11-27; the simulated sequence differs
    in its last bits between machines): 2.91 cm without, 1.50 with, 25 frames fused (5 refused
    as "too few agreeing"). Since the range is measured on surface points in 4-px cells
    instead of a half-resolution render (2026-11-28, an Intel Xeon): 2.95 cm without, 1.37
    with (1.78 with the render on that machine), 25 frames fused (5 refused as "too few
    agreeing"). Bounds: 0.75x, and 60 % of the frames. Both runs leave the poses
    as the oracle gives them (``pose_gate.depth_align`` off): the alignment moves them along the ray
    onto the depth frames too, which is not what this test measures (with it: 3.94 cm plain,
    1.53 cm ranged, 19 frames fused, 11 refused)."""
    seq = fast_sequence
    oracle = {"std_translation": 0.02, "std_rotation": 0.03}
    plain, _ = make_tracker(seq, oracle=oracle, pose_gate={"depth_align": False})
    ranged, _ = make_tracker(seq, oracle=oracle, depth_fusion={"range": True},
                             pose_gate={"depth_align": False})
    a, b = plain.track(seq), ranged.track(seq)
    assert plain.stats.depth_ranges == 0
    frames = len(seq.depth_times_us)
    assert ranged.stats.depth_ranges >= 0.6 * frames, ranged.stats.depth_ranges_skipped
    e_plain, e_ranged = _depth_rmse_cm(a, seq, 150_000), _depth_rmse_cm(b, seq, 150_000)
    assert e_ranged < 0.75 * e_plain, (e_plain, e_ranged)


def test_depth_range_config_is_checked(fast_sequence) -> None:
    with pytest.raises(ConfigError, match="depth.source 'sensor'"):
        TrackerConfig.from_dict({"depth_fusion": {"range": True}, "depth": {"source": "model"}})
    with pytest.raises(ConfigError, match="range_std_m"):
        TrackerConfig.from_dict({"depth_fusion": {"range_std_m": 0.0}})
    cube = np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)])
    with pytest.raises(ConfigError, match="mesh"):
        Tracker(TrackerConfig(depth_fusion={"range": True}), camera=CAM, mesh=cube)
    # the velocity baseline takes poses only to initialise: no range there
    velocity, _ = make_tracker(fast_sequence, method="velocity", depth_fusion={"range": True})
    assert velocity.depth_fusion is None


@pytest.mark.parametrize("method", ["pose", "frame-flow", "ge"])
def test_every_pose_filter_method_measures_ranges(fast_sequence, method) -> None:
    """The baselines with a pose filter measure ranges too (frame-flow measures depth in the
    RGB camera and carries the range into the event camera's frame). Every depth frame after
    the first pose is fused or refused with a reason: a prediction far off across the ray
    (``pose`` and ``ge`` lag this fast box by centimetres) is refused, not fused."""
    seq = fast_sequence
    tracker, _ = make_tracker(seq, method=method, depth_fusion={"range": True})
    traj = tracker.track(seq)
    st = tracker.stats
    known = {"no pose", "too few cells", "too few agreeing", "offset too large"}
    assert set(st.depth_ranges_skipped) <= known
    before_first_pose = int(np.ceil(tracker.config.pose_latency_ms * 1e3 / np.diff(
        seq.depth_times_us.numpy()).mean())) + 1
    frames = len(seq.depth_times_us)
    assert st.depth_ranges + sum(st.depth_ranges_skipped.values()) >= frames - before_first_pose
    if method != "ge":
        assert st.depth_ranges >= 5
    assert np.isfinite(traj.poses.numpy()[traj.status.numpy() > 0]).all()


def test_the_range_needs_no_renderer(scene, monkeypatch) -> None:
    """The range comes from surface points, not a render: with OpenGL unavailable the tracker
    still builds and measures it (the renderer is the scene fixture's reference only)."""
    import evtrack.sim.renderer as renderer

    class NoGL:
        def __init__(self, *args, **kwargs) -> None:
            raise renderer.RendererUnavailableError("no EGL here (test)")

    monkeypatch.setattr(renderer, "Renderer", NoGL)
    box, truth, depth, _, _ = scene
    res = DepthRange(box, CAM).measure(depth, truth)
    assert res.ok and abs(res.distance - float(np.linalg.norm(truth[:3, 3]))) < 0.001
    tracker = Tracker(TrackerConfig(depth_fusion={"range": True}), camera=CAM, mesh=box)
    assert tracker.depth_fusion.depth_range is not None


def test_the_removed_render_scale_field_says_what_to_do() -> None:
    with pytest.raises(ConfigError, match="'depth_range_scale' was removed: .*delete the field"):
        TrackerConfig.from_dict({"depth_fusion": {"range": True}, "depth_range_scale": 0.5})
