"""The estimator's second pass on a crop around each detection (``DecodeConfig.crop_refine``).

The 'network' here reads its input: the test image holds one coloured dot per keypoint (the
projection of the true pose, distortion included), and the network puts a belief peak where
it finds each dot, with a fixed error of a few of *its own* pixels per keypoint, as a real
network has. A crop that enlarges the object divides that error by the zoom factor, so the
second pass must land nearer the truth; wrong crop intrinsics or a wrong map back to the
image would land far from it.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.models import Cuboid, DecodeConfig, PoseEstimator
from evtrack.models.crop_refine import crop_window, halfway_rotation, warp_crop

CUBOID = Cuboid((0.08, 0.12, 0.05))
STRIDE = 8
# a fixed error per keypoint in the network's pixels (the same in every pass)
KEYPOINT_ERROR = np.array([[2.0, -1.5], [-2.0, 1.0], [1.5, 2.0], [-1.0, -2.0], [2.0, 1.5],
                           [-1.5, -1.0], [1.0, -2.0], [-2.0, 2.0], [0.5, -0.5]])


def _code(k: int) -> int:
    return 40 + 20 * k


def pose_at(translation, euler=(0.4, -0.6, 0.3)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", euler).as_matrix()
    T[:3, 3] = translation
    return T


def paint(camera: PinholeCamera, poses: list[np.ndarray]) -> np.ndarray:
    """A black image with a 5x5 dot per keypoint of each pose: red = 40 + 20 k, green 255."""
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    dist = None if camera.dist is None else camera.dist.numpy()
    for pose in poses:
        for k, (u, v) in enumerate(CUBOID.project(pose, camera.K().numpy(), dist)):
            x, y = int(round(u)), int(round(v))
            image[max(0, y - 2):y + 3, max(0, x - 2):x + 3] = (_code(k), 255, 0)
    return image


class DotNetwork(PoseEstimator):
    """Finds the dots in its input and answers with belief peaks (plus ``KEYPOINT_ERROR``)
    and affinity fields towards the centroid, one instance per cluster of dots."""

    calls: list[tuple[int, ...]]
    image_shape = (240, 320)  # (H, W) of the first pass's input; any other is a crop

    def peaks(self, k: int, dots: np.ndarray, centroids: np.ndarray, crop: bool) -> np.ndarray:
        """Where the network puts keypoint ``k``'s peaks: at its (M, 2) dots, plus the error."""
        return dots + KEYPOINT_ERROR[k]

    def run_network(self, batch):
        self.calls = [*getattr(self, "calls", []), batch.shape]
        b, _, h, w = batch.shape
        mean, std = np.asarray(self.mean)[:, None, None], np.asarray(self.std)[:, None, None]
        rgb = (batch * std + mean) * 255.0
        gy, gx = np.mgrid[0:h // STRIDE, 0:w // STRIDE]
        px, py = gx * STRIDE + (STRIDE - 1) / 2, gy * STRIDE + (STRIDE - 1) / 2
        belief = np.zeros((b, 9, h // STRIDE, w // STRIDE), np.float32)
        affinity = np.zeros((b, 16, h // STRIDE, w // STRIDE), np.float32)
        for i in range(b):
            red, green = rgb[i, 0], rgb[i, 1]
            found = {}  # keypoint -> (M, 2) dots, one per connected blob of its colour
            for k in range(9):
                hit = ((np.abs(red - _code(k)) < 4) & (green > 250)).astype(np.uint8)
                n, labels = cv2.connectedComponents(hit)
                found[k] = np.array([[xs.mean(), ys.mean()] for xs, ys in (
                    np.nonzero(labels.T == j) for j in range(1, n))]).reshape(-1, 2)
            centroids = found[8]
            crop = batch.shape[2:] != self.image_shape
            for k in range(9):
                found[k] = self.peaks(k, found[k], centroids, crop)
            for k, points in found.items():
                for u, v in points:
                    belief[i, k] = np.maximum(
                        belief[i, k], np.exp(-((px - u) ** 2 + (py - v) ** 2) / 2 / 4.0**2))
                    if k < 8 and len(centroids):
                        d = centroids[np.argmin(np.hypot(*(centroids - (u, v)).T))] - (u, v)
                        d /= np.linalg.norm(d)
                        disc = np.hypot(px - u, py - v) < 12
                        affinity[i, 2 * k][disc], affinity[i, 2 * k + 1][disc] = d
        return belief, affinity


def errors(det, truth: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg)."""
    pose = det.pose.numpy()
    rot = Rotation.from_matrix(pose[:3, :3].T @ truth[:3, :3]).magnitude()
    return float(np.linalg.norm(pose[:3, 3] - truth[:3, 3])), float(np.degrees(rot))


CAM = PinholeCamera(400.0, 400.0, 159.5, 119.5, 320, 240)
CAM_DIST = PinholeCamera(400.0, 400.0, 159.5, 119.5, 320, 240,
                         dist=np.array([-0.25, 0.08, 0.001, -0.0005, 0.0]))


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_the_crop_pass_divides_the_keypoint_error_by_the_zoom(camera):
    truth = pose_at((0.03, -0.02, 0.9))  # far: the box spans ~60 px of 320
    image = paint(camera, [truth])
    one = DotNetwork(camera, CUBOID, decode=DecodeConfig(crop_refine=0.0))
    two = DotNetwork(camera, CUBOID, decode=DecodeConfig(crop_blend_max_deg=0.0))  # crop's own
    (first,) = one(image)
    (second,) = two(image)
    assert len(one.calls) == 1 and len(two.calls) == 2
    size = two.crop_size(camera.width)
    assert two.calls[1] == (1, 3, size, size) and size == 160  # 0.5 of 320
    t1, r1 = errors(first, truth)
    t2, r2 = errors(second, truth)
    assert t1 > 0.005  # the first pass's error is a real one (several mm at 0.9 m)
    zoom = crop_window(first.pose.numpy(), CUBOID, camera.K().numpy(),
                       None if camera.dist is None else camera.dist.numpy(), size, 1.3).scale
    assert zoom > 1.6
    assert t2 < 0.75 * t1 and r2 < r1
    # keypoints come back in image pixels, near the true projections (error / zoom)
    dist = None if camera.dist is None else camera.dist.numpy()
    projected = CUBOID.project(truth, camera.K().numpy(), dist)
    off = np.linalg.norm(second.keypoints.numpy() - projected, axis=1)
    assert off.max() < np.linalg.norm(KEYPOINT_ERROR, axis=1).max() / zoom + 1.0
    assert second.reprojection_error_px < first.reprojection_error_px
    # the first pass's detection, which the crop's replaced, is kept as its alternative
    (alternative,) = second.alternatives
    np.testing.assert_array_equal(alternative.pose.numpy(), first.pose.numpy())
    np.testing.assert_array_equal(alternative.keypoints.numpy(), first.keypoints.numpy())
    assert alternative.confidence == first.confidence and alternative.alternatives == ()


def test_the_detection_turns_halfway_to_the_first_pass_where_the_passes_agree():
    truth = pose_at((0.03, -0.02, 0.9))
    image = paint(CAM, [truth])
    (first,) = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_refine=0.0))(image)
    (crop,) = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_blend_max_deg=0.0))(image)
    (blended,) = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_blend_max_deg=45.0))(image)
    assert DecodeConfig().crop_blend_max_deg == 0.0  # opt-in
    a, b = crop.pose.numpy(), first.pose.numpy()
    assert not np.allclose(a[:3, :3], b[:3, :3])  # the passes err apart (the premise)
    np.testing.assert_allclose(blended.pose.numpy(), halfway_rotation(a, b, 45.0), atol=1e-12)
    np.testing.assert_array_equal(blended.pose.numpy()[:3, 3], a[:3, 3])  # the crop's position
    # keypoints, confidence and reprojection error are the crop's; both passes' poses are kept
    np.testing.assert_array_equal(blended.keypoints.numpy(), crop.keypoints.numpy())
    assert blended.confidence == crop.confidence
    kept = blended.alternatives
    assert len(kept) == 2 and all(d.alternatives == () for d in kept)
    assert {tuple(d.pose.numpy().ravel()) for d in kept} == {tuple(a.ravel()), tuple(b.ravel())}


@pytest.mark.parametrize("angles", [(0.0, 0.6), (-0.3, 0.2), (0.5, 0.5)])
def test_halfway_rotation_halves_the_geodesic_and_keeps_the_first_translation(angles):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    base = pose_at((0.1, 0.0, 0.7))
    a, b = base.copy(), base.copy()
    a[:3, :3] = base[:3, :3] @ Rotation.from_rotvec(angles[0] * axis).as_matrix()
    b[:3, :3] = base[:3, :3] @ Rotation.from_rotvec(angles[1] * axis).as_matrix()
    b[:3, 3] += (0.0, 0.01, 0.06)
    mid = halfway_rotation(a, b, 90.0)
    expected = base[:3, :3] @ Rotation.from_rotvec(0.5 * sum(angles) * axis).as_matrix()
    np.testing.assert_allclose(mid[:3, :3], expected, atol=1e-12)
    np.testing.assert_array_equal(mid[:3, 3], a[:3, 3])
    np.testing.assert_allclose(halfway_rotation(b, a, 90.0)[:3, :3], mid[:3, :3], atol=1e-12)
    np.testing.assert_array_equal(mid[3], [0, 0, 0, 1])
    apart = np.degrees(abs(angles[1] - angles[0]))  # farther apart than max_deg: no mean
    assert halfway_rotation(a, b, apart + 0.5) is not None
    if apart > 0.5:
        assert halfway_rotation(a, b, apart - 0.5) is None


def test_a_close_object_is_shrunk_and_the_crop_may_leave_the_image():
    truth = pose_at((0.05, 0.02, 0.32))  # close and off-centre: the crop reaches past the edge
    image = paint(CAM, [truth])
    est = DotNetwork(CAM, CUBOID)
    (det,) = est(image)
    window = crop_window(det.pose.numpy(), CUBOID, CAM.K().numpy(), None, est.crop_size(320), 1.3)
    corners = window.to_image(np.array([[0.0, 0.0], [159.0, 159.0]]))
    assert window.scale < 1.0  # shrunk
    assert (corners[1] > [319, 239]).any() or (corners[0] < 0).any()  # reaches past the image
    t, r = errors(det, truth)
    assert t < 0.01 and r < 3.0


def test_each_image_and_instance_gets_its_own_crop():
    a, b = pose_at((-0.1, 0.0, 0.8)), pose_at((0.1, 0.03, 0.8), euler=(-0.2, 0.5, 1.0))
    images = [paint(CAM, [a, b]), paint(CAM, [b])]
    est = DotNetwork(CAM, CUBOID)
    out = est.estimate_batch(images)
    one = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_refine=0.0)).estimate_batch(images)
    assert [len(d) for d in out] == [2, 1]
    assert len(est.calls) == 2 and est.calls[1][0] == 3  # one network call for three crops
    for dets, first, truths in ((out[0], one[0], [a, b]), (out[1], one[1], [b])):
        for truth in truths:
            refined = sorted(errors(d, truth)[0] for d in dets)
            assert refined[0] < min(errors(d, truth)[0] for d in first)  # its own crop
            assert refined[1:] == [] or refined[1] > 0.15  # the other took the other object


class BlindInCrops(DotNetwork):
    """Finds nothing in crops (a second pass that fails)."""

    def run_network(self, batch):
        belief, affinity = super().run_network(batch)
        if batch.shape[2:] != (240, 320):
            belief[:] = 0.0
        return belief, affinity


def test_a_crop_without_the_object_keeps_the_first_pose():
    truth = pose_at((0.0, 0.0, 0.7))
    image = paint(CAM, [truth])
    (first,) = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_refine=0.0))(image)
    blind = BlindInCrops(CAM, CUBOID)
    (kept,) = blind(image)
    assert len(blind.calls) == 2
    np.testing.assert_array_equal(kept.pose.numpy(), first.pose.numpy())
    np.testing.assert_array_equal(kept.keypoints.numpy(), first.keypoints.numpy())
    assert kept.alternatives == ()  # nothing was replaced


class ConfusedInCrops(DotNetwork):
    """Sees the object in crops but puts its corners there where no cuboid fits them: each
    corner's peak moves along the ray from the centroid by its own factor (the affinity still
    points at the centroid, so the corners join the instance), as the corner maps of a network
    that mixes the corners of a near or symmetric object up do."""

    RADIAL = np.array([0.73, 1.09, 0.71, 1.41, -0.61, 0.52, 0.36, -0.56])

    def peaks(self, k, dots, centroids, crop):
        dots = super().peaks(k, dots, centroids, crop)
        if not crop or k == 8 or not len(centroids) or not len(dots):
            return dots
        return dots + self.RADIAL[k] * (dots - centroids[0])


@pytest.mark.parametrize("search_below", [0.1, 0.3])
def test_a_failed_crop_reading_does_not_replace_a_confident_first_pass(search_below):
    """The first pass's detection stays where the crop's reading is less confident than
    ``search_below`` (the decoder's mark of a failed fit) and the first pass's is not: a
    failed second look must not demote a detection below other instances (a distractor)."""
    truth = pose_at((0.0, 0.0, 0.7))
    image = paint(CAM, [truth])
    decode = DecodeConfig(search_below=search_below)
    (first,) = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_refine=0.0,
                                                           search_below=search_below))(image)
    assert first.confidence >= search_below
    confused = ConfusedInCrops(CAM, CUBOID, decode=decode)
    (kept,) = confused(image)
    assert len(confused.calls) == 2
    np.testing.assert_array_equal(kept.pose.numpy(), first.pose.numpy())
    assert kept.confidence == first.confidence
    assert kept.alternatives, "the crop's reading is kept as an alternative"
    assert all(alt.confidence < search_below for alt in kept.alternatives)  # the premise
    # with no failure mark (search_below 0) the crop's reading replaces the first's pose
    (replaced,) = ConfusedInCrops(CAM, CUBOID, decode=DecodeConfig(search_below=0.0))(image)
    assert not np.array_equal(replaced.pose.numpy(), first.pose.numpy())


class BlurredInCrops(ConfusedInCrops):
    """A crop pass that finds the object but fits its corners worse than the first pass (as
    a crop enlarging a motion-blurred object does): a valid, less confident reading."""

    RADIAL = np.array([0.48, 1.49, -0.37, 1.48, 0.02, 0.27, 1.2, 0.24])


class BlurredEverywhere(BlurredInCrops):
    """:class:`BlurredInCrops`'s corners in the first pass too."""

    image_shape = (0, 0)


def test_a_detection_is_ranked_by_the_better_of_its_two_looks():
    """The crop's pose replaces the first pass's; the confidence stays the first pass's where
    that is higher, so a crop that sees the object worse than a distractor's crop sees the
    distractor does not rank the object below it."""
    truth = pose_at((0.0, 0.0, 0.7))
    image = paint(CAM, [truth])
    (first,) = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_refine=0.0))(image)
    (refined,) = BlurredInCrops(CAM, CUBOID)(image)
    # the crop's pose (a valid reading: a failed one would leave the first pass's), which
    # fits its corners worse than the first pass did
    assert not np.array_equal(refined.pose.numpy(), first.pose.numpy())
    assert refined.reprojection_error_px > 2 * first.reprojection_error_px
    assert refined.confidence == first.confidence
    (alternative,) = refined.alternatives
    np.testing.assert_array_equal(alternative.pose.numpy(), first.pose.numpy())
    # the crop's own confidence, from a network whose first pass is as bad as its crop
    (crop_only,) = BlurredEverywhere(CAM, CUBOID, decode=DecodeConfig(crop_refine=0.0))(image)
    assert DecodeConfig().search_below <= crop_only.confidence < first.confidence


def test_crop_intrinsics_see_the_crop_as_the_camera_sees_the_image():
    """``A K`` with the same distortion projects a point where the affine map puts its image
    projection: the crop's pinhole model is exact, not an approximation."""
    rng = np.random.default_rng(0)
    K, dist = CAM_DIST.K().numpy(), CAM_DIST.dist.numpy()
    window = crop_window(pose_at((0.02, 0.01, 0.6)), CUBOID, K, dist, 96, 1.3)
    cube = Cuboid((0.3, 0.2, 0.1))
    for _ in range(5):
        pose = pose_at(rng.uniform(-0.05, 0.05, 3) + [0, 0, 0.7], rng.uniform(-1, 1, 3))
        in_image = cube.project(pose, K, dist)
        in_crop = cube.project(pose, window.intrinsics(K), dist)
        np.testing.assert_allclose(in_crop, in_image * window.scale + window.offset, atol=1e-9)
        np.testing.assert_allclose(window.to_image(in_crop), in_image, atol=1e-9)


def test_crop_window_centres_the_box_and_warp_follows_it():
    K = CAM.K().numpy()
    pose = pose_at((0.01, 0.0, 0.6))
    window = crop_window(pose, CUBOID, K, None, 64, 1.5)
    uv = CUBOID.project(pose, K)[:8] * window.scale + window.offset
    # the box's corners are placed on a 1/8 px grid first (the same crop for poses a hair
    # apart): centred and sized to within that grid, scaled into the crop
    grid = window.scale / 8
    np.testing.assert_allclose((uv.min(0) + uv.max(0)) / 2, [31.5, 31.5], atol=grid / 2 + 1e-9)
    assert (uv.max(0) - uv.min(0)).max() == pytest.approx(64 / 1.5, abs=grid + 1e-9)
    # the warp moves a pixel where the window says (bilinear: exact at an integer target)
    image = np.zeros((240, 320, 3), np.uint8)
    image[100:141, 150:191] = 200
    crop = warp_crop(image, window, (7, 7, 7))
    ys, xs = np.nonzero(crop[:, :, 0] == 200)
    back = window.to_image(np.stack([xs, ys], 1))
    assert ((back >= [149.5, 99.5]) & (back <= [190.5, 140.5])).all()
    # behind the camera or degenerate: no window
    behind = pose.copy()
    behind[2, 3] = -0.6
    assert crop_window(behind, CUBOID, K, None, 64, 1.3) is None
    nan = pose.copy()
    nan[0, 3] = np.nan
    assert crop_window(nan, CUBOID, K, None, 64, 1.3) is None


def test_crop_settings_are_checked():
    with pytest.raises(ConfigError, match="crop_refine"):
        DecodeConfig(crop_refine=-0.1)
    with pytest.raises(ConfigError, match="crop_refine"):
        DecodeConfig(crop_refine=float("nan"))
    with pytest.raises(ConfigError, match="crop_margin"):
        DecodeConfig(crop_margin=0.9)
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="prior_recrop"):
            DecodeConfig(prior_recrop=bad)
    for bad in (-1.0, 181.0, float("nan")):
        with pytest.raises(ConfigError, match="crop_blend_max_deg"):
            DecodeConfig(crop_blend_max_deg=bad)
    est = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_refine=0.01))
    assert est.crop_size(320) == 2 * STRIDE  # at least two output cells


def _nudged(pose: np.ndarray, shift_m, turn_deg: float) -> np.ndarray:
    out = pose.copy()
    out[:3, 3] += shift_m
    out[:3, :3] = Rotation.from_euler("z", turn_deg, degrees=True).as_matrix() @ out[:3, :3]
    return out


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_estimate_near_runs_the_crop_pass_alone_around_a_good_prior(camera):
    truth = pose_at((0.03, -0.02, 0.9))
    image = paint(camera, [truth])
    est = DotNetwork(camera, CUBOID, decode=DecodeConfig(crop_blend_max_deg=0.0))
    est.calls = []
    (near,) = est.estimate_near(image, _nudged(truth, (0.001, -0.001, 0.002), 0.5))
    size = est.crop_size(camera.width)
    assert est.calls == [(1, 3, size, size)]  # one call: the crop, no whole-image pass
    t_near, r_near = errors(near, truth)
    (one_pass,) = DotNetwork(camera, CUBOID, decode=DecodeConfig(crop_refine=0.0))(image)
    t_one, r_one = errors(one_pass, truth)
    # the zoom's gain without the whole-image pass: the keypoint errors shrink as in the
    # two-pass estimate's crop
    assert t_near < 0.75 * t_one and r_near < r_one
    dist = None if camera.dist is None else camera.dist.numpy()
    projected = CUBOID.project(truth, camera.K().numpy(), dist)
    assert np.linalg.norm(near.keypoints.numpy() - projected, axis=1).max() < 3.0


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_estimate_near_places_the_crop_again_on_its_detection_when_the_prior_is_off(camera):
    truth = pose_at((0.03, -0.02, 0.9))
    image = paint(camera, [truth])
    est = DotNetwork(camera, CUBOID, decode=DecodeConfig(crop_blend_max_deg=0.0))
    size = est.crop_size(camera.width)
    (one_pass,) = DotNetwork(camera, CUBOID, decode=DecodeConfig(crop_refine=0.0))(image)
    t_one, r_one = errors(one_pass, truth)
    for shift, turn in (((0.01, -0.005, 0.02), 8.0), ((-0.01, 0.005, -0.02), -8.0)):
        est.calls = []
        (near,) = est.estimate_near(image, _nudged(truth, shift, turn))
        assert est.calls == [(1, 3, size, size)] * 2  # the prior's crop, then the detection's
        # the second crop sits about where the two-pass estimate's does: the zoom's gain,
        # not the prior's error (2 cm and 8 deg)
        t_near, r_near = errors(near, truth)
        assert t_near < 0.75 * t_one and r_near < r_one
        (first,) = near.alternatives  # the prior crop's detection, as the first pass's is
        assert not np.array_equal(first.pose.numpy(), near.pose.numpy())
    # prior_recrop 1: the prior's crop is always kept (one call), however far off it is
    loose = DotNetwork(camera, CUBOID, decode=DecodeConfig(crop_blend_max_deg=0.0,
                                                           prior_recrop=1.0))
    loose.calls = []
    loose.estimate_near(image, _nudged(truth, (0.01, -0.005, 0.02), 8.0))
    assert len(loose.calls) == 1


def test_estimate_near_falls_back_to_the_whole_image_when_the_object_is_not_there():
    truth = pose_at((0.03, -0.02, 0.9))
    image = paint(CAM, [truth])
    est = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_blend_max_deg=0.0))
    (two_pass,) = est(image)
    size = est.crop_size(CAM.width)
    # a prior 15 cm away (~65 px): its crop holds at most part of the object, off-centre
    for prior in (_nudged(truth, (-0.15, 0.0, 0.0), 0.0), _nudged(truth, (0.0, 0.12, 0.0), 0.0)):
        est.calls = []
        (found,) = est.estimate_near(image, prior)
        assert est.calls[0] == (1, 3, size, size) and len(est.calls) == 3  # crop, image, crop
        np.testing.assert_array_equal(found.pose.numpy(), two_pass.pose.numpy())
    # a prior with no usable crop (behind the camera, not finite): the whole image at once
    behind = _nudged(truth, (0.0, 0.0, -2.0), 0.0)
    nan = np.full((4, 4), np.nan)
    for prior in (behind, nan):
        est.calls = []
        (found,) = est.estimate_near(image, prior)
        assert len(est.calls) == 2
        np.testing.assert_array_equal(found.pose.numpy(), two_pass.pose.numpy())
    with pytest.raises(ValueError, match=r"prior must be a \(4, 4\) pose"):
        est.estimate_near(image, np.eye(3))
    # one pass configured: the prior is not used
    one = DotNetwork(CAM, CUBOID, decode=DecodeConfig(crop_refine=0.0))
    (plain,) = one(image)
    one.calls = []
    (found,) = one.estimate_near(image, truth)
    assert len(one.calls) == 1
    np.testing.assert_array_equal(found.pose.numpy(), plain.pose.numpy())
