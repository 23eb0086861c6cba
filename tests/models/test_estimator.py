"""The shared PoseEstimator pipeline (input checks, resize, padding, decoding, PnP)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from evtrack.camera import PinholeCamera
from evtrack.errors import ConfigError
from evtrack.models import (
    Cuboid,
    DecodeConfig,
    PoseEstimator,
    TorchPoseEstimator,
    create,
    preprocess,
)
from evtrack.models.fold_batchnorm import fold_batchnorm

ONE_PASS = DecodeConfig(crop_refine=0.0)

CAM = PinholeCamera(400.0, 400.0, 159.5, 119.5, 320, 240)
CUBOID = Cuboid((0.08, 0.12, 0.05))


def truth_pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [0.4, -0.6, 0.3]).as_matrix()
    T[:3, 3] = (0.02, -0.01, 0.5)
    return T


class AnalyticEstimator(PoseEstimator):
    """A 'network' that returns the ideal maps of ``truth_pose`` for whatever input it gets
    (so one pass only: the second pass's crops would get the whole image's maps)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, decode=ONE_PASS, **kwargs)

    def run_network(self, batch):
        b, _, h, w = batch.shape
        # the input was resized by input_scale from the 320x240 camera image (then padded)
        s = self.input_scale
        uv = (CUBOID.project(truth_pose(), CAM.K().numpy()) + 0.5) * s - 0.5
        gy, gx = np.mgrid[0 : h // 8, 0 : w // 8]
        px, py = gx * 8 + 3.5, gy * 8 + 3.5
        belief = np.stack([np.exp(-((px - u) ** 2 + (py - v) ** 2) / 2 / 6.0**2) for u, v in uv])
        affinity = np.zeros((16, h // 8, w // 8))
        for k in range(8):
            d = uv[8] - uv[k]
            d /= np.linalg.norm(d)
            disc = np.hypot(px - uv[k, 0], py - uv[k, 1]) < 12
            affinity[2 * k][disc], affinity[2 * k + 1][disc] = d
        self.seen_shape = batch.shape
        return np.repeat(belief[None], b, 0), np.repeat(affinity[None], b, 0)


@pytest.mark.parametrize("scale,expected_shape", [(1.0, (1, 3, 240, 320)), (0.5, (1, 3, 120, 160)),
                                                  (0.3, (1, 3, 72, 96))])
def test_pipeline_recovers_the_pose(scale, expected_shape):
    est = AnalyticEstimator(CAM, CUBOID, object_name="box", input_scale=scale)
    image = np.zeros((240, 320, 3), np.uint8)
    (det,) = est(image)
    assert est.seen_shape == expected_shape  # 0.3 * 240 = 72, 0.3 * 320 = 96: padded already
    T = truth_pose()
    assert np.linalg.norm(det.pose[:3, 3].numpy() - T[:3, 3]) < 2e-3
    err = Rotation.from_matrix(det.pose[:3, :3].numpy().T @ T[:3, :3]).magnitude()
    assert np.degrees(err) < 0.5
    assert det.object_name == "box"
    assert det.keypoints.shape == (9, 2)


def test_batch_and_K_matrix_camera():
    est = AnalyticEstimator(CAM.K().numpy(), CUBOID)
    images = [np.zeros((240, 320, 3), np.uint8)] * 3
    out = est.estimate_batch(images)
    assert len(out) == 3 and all(len(d) == 1 for d in out)
    assert est.estimate_batch([]) == []


def test_preprocess_normalises_and_pads():
    rgb = np.full((20, 30, 3), 255, np.uint8)
    x, scale = preprocess(rgb, (0.5, 0.5, 0.5), (0.25, 0.5, 1.0), 1.0, 8)
    assert x.shape == (3, 24, 32) and x.dtype == np.float32 and scale == (1.0, 1.0)
    np.testing.assert_allclose(x[:, :20, :30].reshape(3, -1).mean(1), [2.0, 1.0, 0.5])
    assert np.all(x[:, 20:, :] == 0) and np.all(x[:, :, 30:] == 0)
    x2, scale2 = preprocess(rgb, (0, 0, 0), (1, 1, 1), 0.5, 8)
    assert x2.shape == (3, 16, 16) and scale2 == (0.5, 0.5)


def test_preprocess_matches_the_plain_formula_on_random_images():
    rng = np.random.default_rng(3)
    mean, std = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
    for h, w, scale in ((37, 53, 1.0), (48, 64, 1.0), (61, 90, 0.5)):
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        x, (sx, sy) = preprocess(rgb, mean, std, scale, 8)
        if scale != 1.0:
            rgb = cv2.resize(rgb, (round(w * scale), round(h * scale)),
                             interpolation=cv2.INTER_AREA)
        ref = ((rgb / 255.0 - mean) / std).transpose(2, 0, 1)
        nh, nw = ref.shape[1:]
        assert x.shape == (3, -(-nh // 8) * 8, -(-nw // 8) * 8) and x.flags.c_contiguous
        np.testing.assert_allclose(x[:, :nh, :nw], ref, atol=2e-6)
        assert np.all(x[:, nh:] == 0) and np.all(x[:, :, nw:] == 0)
        assert (sx, sy) == (nw / w, nh / h)


def test_folded_batchnorm_gives_the_same_maps_and_leaves_the_network_alone():
    torch.manual_seed(0)
    net = create("dope_lite_small")
    # non-trivial running statistics and affine parameters: a fresh BN is the identity
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    net.train()
    before = {k: v.clone() for k, v in net.state_dict().items()}
    folded, count = fold_batchnorm(net)
    n_bn = sum(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    assert count == n_bn > 0
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert net.training and not folded.training  # the original keeps its mode and weights
    torch.testing.assert_close(net.state_dict(), before)
    x = torch.randn(2, 3, 64, 96)
    with torch.inference_mode():
        ref = net.eval()(x)
        out = folded(x)
    for a, b in zip(out, ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
    est = TorchPoseEstimator(net, CAM, cuboid=CUBOID)
    plain = TorchPoseEstimator(net, CAM, cuboid=CUBOID, fold_batchnorm=False)
    assert plain.net is net and est.net is not net
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in est.net.modules())


def test_bad_inputs_are_clear_errors():
    est = TorchPoseEstimator(create("dope_lite_tiny"), CAM, cuboid=CUBOID)
    with pytest.raises(ValueError, match="uint8"):
        est(np.zeros((240, 320, 3), np.float32))
    with pytest.raises(ValueError, match="uint8"):
        est(np.zeros((240, 320), np.uint8))
    with pytest.raises(ValueError, match="numpy array"):
        est(torch.zeros(240, 320, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="camera is 320x240"):
        est(np.zeros((480, 640, 3), np.uint8))
    # a batch or a CHW image is named as such, not as an image of the wrong size
    with pytest.raises(ValueError, match=r"\(H, W, 3\) RGB image, got uint8 \(1, 240, 320, 3\)"):
        est(np.zeros((1, 240, 320, 3), np.uint8))
    with pytest.raises(ValueError, match=r"\(H, W, 3\) RGB image, got uint8 \(3, 240, 320\)"):
        est(np.zeros((3, 240, 320), np.uint8))
    with pytest.raises(ConfigError, match="no weights record"):
        TorchPoseEstimator(create("dope_lite_tiny"), CAM)
    with pytest.raises(ConfigError, match="input_scale"):
        TorchPoseEstimator(create("dope_lite_tiny"), CAM, cuboid=CUBOID, input_scale=0)


def test_torch_estimator_runs_a_real_network():
    torch.manual_seed(0)
    est = TorchPoseEstimator(create("dope_lite_tiny"), CAM, cuboid=CUBOID)
    belief, affinity, scale = est.predict_maps([np.zeros((240, 320, 3), np.uint8)])
    assert belief.shape == (1, 9, 30, 40) and affinity.shape == (1, 16, 30, 40)
    assert isinstance(est(np.zeros((240, 320, 3), np.uint8)), list)


def test_default_input_scale_is_the_training_resolution(tmp_path):
    from evtrack.models import WeightsRecord, save_weights

    net = create("dope_lite_tiny")
    record = WeightsRecord(arch="dope_lite_tiny", object_name="box", cuboid=CUBOID,
                           input_size=(120, 160))
    path = save_weights(tmp_path / "w.pt", net, record)
    cam640 = PinholeCamera(800.0, 800.0, 319.5, 239.5, 640, 480)
    est = TorchPoseEstimator.from_weights(path, cam640)
    assert est.input_scale == pytest.approx(0.25)
    belief, _, (sx, sy) = est.predict_maps([np.zeros((480, 640, 3), np.uint8)])
    assert belief.shape == (1, 9, 15, 20) and (sx, sy) == (0.25, 0.25)
    assert TorchPoseEstimator.from_weights(path, cam640, input_scale=1.0).input_scale == 1.0
    # a bare K: the image size is unknown, so images are used as they come
    assert TorchPoseEstimator.from_weights(path, CAM.K().numpy()).input_scale == 1.0
