"""Appearance refinement (evtrack.models.AppearanceRefiner): poses recovered on renders with
known poses, its Jacobian against finite differences, what it measures and what it refuses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.models import AppearanceRefineConfig, AppearanceRefiner
from evtrack.sim.frames import linear_to_srgb, luminance
from evtrack.sim.objects import ObjectMesh, procedural_object

CAM = PinholeCamera(300.0, 300.0, 159.5, 119.5, 320, 240)


def pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def turned(T: np.ndarray, axis_obj, deg: float, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``T`` turned by ``deg`` about an object-frame axis through its origin, then shifted
    (camera frame, m)."""
    out = T.copy()
    axis = np.asarray(axis_obj, float) / np.linalg.norm(axis_obj)
    out[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(np.radians(deg) * axis).as_matrix()
    out[:3, 3] = T[:3, 3] + np.asarray(shift)
    return out


def angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    R = A[:3, :3].T @ B[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def frame_of(mesh: ObjectMesh, T: np.ndarray, camera: PinholeCamera = CAM,
             background: float = 0.25) -> np.ndarray:
    """The uint8 sRGB frame a camera takes of ``mesh`` at ``T`` before a grey wall, with a
    different exposure (gain 0.8) than the refiner's render."""
    from evtrack.sim.renderer import Renderer

    with Renderer(camera) as r:
        r.set_object(mesh)
        out = r.render(T)
    lin = np.where(out.mask[..., None], 0.8 * out.rgb, background)
    return linear_to_srgb(lin)


@pytest.fixture(scope="module")
def can():
    return procedural_object("can", 3)


@pytest.fixture(scope="module")
def box():
    return procedural_object("box", 1)


CAN_POSE = pose([1.2, 0.3, 0.2], [0.01, -0.005, 0.45])
BOX_POSE = pose([0.5, -0.6, 0.3], [-0.01, 0.01, 0.7])


@pytest.mark.parametrize("deg", [-15.0, 6.0, 20.0])
def test_a_cans_turn_about_its_axis_is_recovered(gl, can, deg) -> None:
    """What no depth frame shows: the can (axis y) turned about its own axis. The label's
    texture brings it back within 0.5°, and the position within 2 mm."""
    frame = frame_of(can, CAN_POSE)
    prior = turned(CAN_POSE, [0, 1, 0], deg, shift=(0.003, -0.002, 0.0))
    res = AppearanceRefiner(can, CAM).refine(prior, frame)
    assert res.refined, res.reason
    assert angle_deg(res.pose, CAN_POSE) < 0.5
    assert np.linalg.norm(res.pose[:3, 3] - CAN_POSE[:3, 3]) < 0.002
    assert res.correlation > 0.95 and res.pixels >= 100


@pytest.mark.parametrize("seed", range(4))
def test_a_box_off_in_every_direction_is_recovered(gl, box, seed) -> None:
    """A box turned 10° about a random axis and shifted 1 cm across the view: within 0.5°
    and 3 mm (the distance along the ray is what an image sees least)."""
    rng = np.random.default_rng(seed)
    frame = frame_of(box, BOX_POSE)
    axis = rng.normal(size=3)
    shift = np.r_[rng.normal(size=2) * 0.007, 0.0]
    prior = turned(BOX_POSE, axis, 10.0, shift)
    res = AppearanceRefiner(box, CAM).refine(prior, frame)
    assert res.refined, res.reason
    assert angle_deg(res.pose, BOX_POSE) < 0.5
    assert np.linalg.norm(res.pose[:3, 3] - BOX_POSE[:3, 3]) < 0.003


def test_the_information_sees_least_along_the_viewing_ray(gl, box) -> None:
    """The fit's covariance (information⁻¹) is largest along the viewing ray: an image shows
    a shift across the view in pixels, a shift along the ray only in the object's size."""
    frame = frame_of(box, BOX_POSE)
    res = AppearanceRefiner(box, CAM).refine(turned(BOX_POSE, [0, 0, 1], 3.0), frame)
    assert res.refined, res.reason
    cov_t = np.linalg.inv(res.information)[:3, :3]
    ray = BOX_POSE[:3, 3] / np.linalg.norm(BOX_POSE[:3, 3])
    across = np.cross(ray, [1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    assert ray @ cov_t @ ray > 10 * (across @ cov_t @ across)


def test_the_jacobian_matches_finite_differences(gl, box) -> None:
    """The Jacobian of the sampled frame with respect to ``[δt, δθ]`` (the pose filter's left
    perturbation: ``R ← exp(δθ) R``, ``t ← t + δt``) against central differences of the
    sampled values themselves."""
    refiner = AppearanceRefiner(box, CAM)
    frame = frame_of(box, BOX_POSE)
    prior = turned(BOX_POSE, [1, 1, 0], 4.0)
    out = refiner._renderer().render(prior)
    image = cv2.GaussianBlur(refiner.frame_luminance(frame), (0, 0), 2.0)
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    vs, us = np.nonzero(cv2.erode(out.mask.astype(np.uint8), np.ones((7, 7), np.uint8)))
    z = out.depth[vs, us].astype(np.float64)
    X_cam = np.stack([(us - CAM.cx) / CAM.fx * z, (vs - CAM.cy) / CAM.fy * z, z], 1)
    X_obj = (X_cam - prior[:3, 3]) @ prior[:3, :3]
    target = luminance(out.rgb[vs, us]).astype(np.float64)
    K = (CAM.fx, CAM.fy, CAM.cx, CAM.cy)
    size = (CAM.width, CAM.height)
    r, J, (sampled, tv) = refiner._linearise(prior, X_obj, target, image, gx, gy, K, size,
                                              values=True)
    gain = float(tv.std()) / float(sampled.std())

    def sampled_at(delta: np.ndarray) -> np.ndarray:
        T = prior.copy()
        T[:3, :3] = Rotation.from_rotvec(delta[3:]).as_matrix() @ prior[:3, :3]
        T[:3, 3] = prior[:3, 3] + delta[:3]
        return refiner._linearise(T, X_obj, target, image, gx, gy, K, size, values=True)[2][0]

    steps = [1e-5] * 3 + [2e-5] * 3
    numeric = np.stack([(sampled_at(h * e) - sampled_at(-h * e)) / (2 * h)
                        for h, e in zip(steps, np.eye(6), strict=True)], 1)
    analytic = J / gain
    # the analytic one samples the blurred image's Sobel gradient, the numeric one differences
    # its bilinear interpolation: they agree up to the interpolation's kinks between pixels
    for k in range(6):
        error = np.linalg.norm(analytic[:, k] - numeric[:, k]) / np.linalg.norm(numeric[:, k])
        assert error < 0.03, (k, error)


def test_a_distorted_camera_s_frame_is_undistorted_first(gl, box) -> None:
    """The renderer is a pinhole: a frame of a camera with lens distortion is undistorted onto
    the same intrinsics before the fit, so the pose comes back as on the pinhole; the same
    frame taken as a pinhole's puts the object (off the image's centre) a centimetre off."""
    dist = np.array([-0.3, 0.1, 0.001, -0.001, 0.0])
    cam = PinholeCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height, dist=dist)
    truth = BOX_POSE.copy()
    truth[:3, 3] = [0.17, 0.11, 0.75]
    pinhole = frame_of(box, truth)
    # each distorted pixel shows what the pinhole image shows at its undistorted place
    u, v = np.meshgrid(np.arange(CAM.width, dtype=np.float64),
                       np.arange(CAM.height, dtype=np.float64))
    K = CAM.K().numpy()
    und = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], 1)[:, None], K, dist, P=K)
    maps = und.reshape(CAM.height, CAM.width, 2).astype(np.float32)
    distorted = cv2.remap(pinhole, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR)
    prior = turned(truth, [0, 1, 0], 6.0)
    res = AppearanceRefiner(box, cam).refine(prior, distorted)
    assert res.refined, res.reason
    assert angle_deg(res.pose, truth) < 1.0
    assert np.linalg.norm(res.pose[:3, 3] - truth[:3, 3]) < 0.004
    naive = AppearanceRefiner(box, CAM).refine(prior, distorted)
    assert not naive.refined or np.linalg.norm(naive.pose[:3, 3] - truth[:3, 3]) > 0.01


def test_what_it_refuses(gl, box) -> None:
    """Each refusal keeps the input pose and says why."""
    refiner = AppearanceRefiner(box, CAM)
    frame = frame_of(box, BOX_POSE)
    behind = BOX_POSE.copy()
    behind[2, 3] = -0.7
    res = refiner.refine(behind, frame)
    assert not res.refined and res.refusal == "not visible"
    np.testing.assert_array_equal(res.pose, behind)
    outside = BOX_POSE.copy()
    outside[0, 3] = 3.0  # far to the right of the image
    assert refiner.refine(outside, frame).refusal == "not visible"
    blank = np.full_like(frame, 90)  # the object is not in the frame at all
    res = refiner.refine(turned(BOX_POSE, [0, 1, 0], 5.0), blank)
    assert not res.refined and res.refusal in ("diverged", "low correlation"), res.refusal
    strict = AppearanceRefiner(box, CAM, AppearanceRefineConfig(max_rotation_deg=2.0))
    res = strict.refine(turned(BOX_POSE, [0, 1, 0], 8.0), frame)
    assert res.refusal == "correction too large" and "8." in res.reason


def test_a_textureless_object_gives_too_few_pixels(gl, box) -> None:
    """A box of one flat colour seen face-on shows one evenly lit face: no texture gradient
    inside its silhouette to align (a turned one would show its edges between faces)."""
    plain = ObjectMesh(box.name, box.vertices, box.faces, box.normals, box.uv,
                       np.full_like(box.texture, 128), box.colors, box.source, box.offset)
    face_on = pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.7])
    res = AppearanceRefiner(plain, CAM).refine(face_on, frame_of(plain, face_on))
    assert not res.refined and res.refusal == "few pixels", res.reason


def test_bad_input_is_named(box) -> None:
    """A mesh without faces, a pose or frame of the wrong shape: errors that name them (no
    renderer needed)."""
    empty = ObjectMesh(box.name, box.vertices, np.zeros((0, 3), np.int32), box.normals, box.uv,
                       box.texture, box.colors, box.source, box.offset)
    with pytest.raises(ConfigError, match="without faces"):
        AppearanceRefiner(empty, CAM)
    millimetres = ObjectMesh(box.name, box.vertices * 1000.0, box.faces, box.normals, box.uv,
                             box.texture, box.colors, box.source, box.offset)
    with pytest.raises(ConfigError, match="must be in metres"):
        AppearanceRefiner(millimetres, CAM)
    refiner = AppearanceRefiner(box, CAM)
    with pytest.raises(ValueError, match="finite"):
        refiner.refine(np.full((4, 4), np.nan), np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(ValueError, match=r"\(240, 320, 3\)"):
        refiner.refine(BOX_POSE, np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(ConfigError, match="levels"):
        AppearanceRefineConfig(levels=())
    with pytest.raises(ConfigError, match="min_correlation"):
        AppearanceRefineConfig(min_correlation=2.0)


def test_ignored_pixels_are_left_out(gl, box) -> None:
    """A flat grey patch (another object in front) over half the box: the fit that leaves the
    patch's pixels out recovers the pose; every pixel ignored leaves nothing to fit."""
    frame = frame_of(box, BOX_POSE).copy()
    from evtrack.sim.renderer import Renderer

    with Renderer(CAM) as r:
        r.set_object(box)
        drawn = r.render(BOX_POSE).mask
    rows, cols = np.nonzero(drawn)
    cover = np.zeros_like(drawn)
    cover[:, : int(np.median(cols))] = True
    frame[cover] = 200  # the occluder's flat surface
    prior = turned(BOX_POSE, [0.3, 1.0, 0.2], 6.0, shift=(0.004, 0.0, 0.0))
    refiner = AppearanceRefiner(box, CAM)
    res = refiner.refine(prior, frame, ignore=cover)
    assert res.refined, res.reason
    assert angle_deg(res.pose, BOX_POSE) < 1.0
    assert np.linalg.norm(res.pose[:3, 3] - BOX_POSE[:3, 3]) < 0.005
    blind = refiner.refine(prior, frame)  # the patch taken for the box: no good fit
    assert not blind.refined or angle_deg(blind.pose, BOX_POSE) > 2.0
    everything = np.ones_like(drawn)
    res = refiner.refine(prior, frame, ignore=everything)
    assert not res.refined and res.refusal == "not visible"
    with pytest.raises(ValueError, match="ignore must be"):
        refiner.refine(prior, frame, ignore=np.zeros((10, 10), bool))
