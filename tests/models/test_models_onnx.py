"""ONNX export and the onnxruntime estimator: same maps and same poses as torch."""

from __future__ import annotations

import dataclasses

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from evtrack.camera import PinholeCamera
from evtrack.models import (
    Cuboid,
    DecodeConfig,
    ExportError,
    OnnxPoseEstimator,
    TorchPoseEstimator,
    WeightsError,
    WeightsRecord,
    create,
    export_onnx,
    preprocess,
    read_onnx_record,
)
from evtrack.train.cuboid_source import CuboidSourceOptions, SyntheticCuboidSource
from evtrack.train.targets import TargetConfig, make_targets

CUBOID = Cuboid((0.1, 0.16, 0.07))
MEAN, STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


def fit_output_layers(net, images, keypoints):
    """Fit each stage's final 1x1 convolution by least squares to the true target maps.

    The random trunk's features are rich enough (256 head channels) for a linear read-out to
    put real, sharp peaks near the keypoints of these images: a network whose decoded poses
    are meaningful and well conditioned, made in well under a second instead of by training.
    """
    x = torch.stack([torch.from_numpy(preprocess(im, MEAN, STD)[0]) for im in images])
    sharp = TargetConfig(sigma_px=8.0)  # one-cell blobs: sharp, well-separated peaks
    targets = torch.stack([torch.from_numpy(np.concatenate(make_targets(kp, im.shape[:2], sharp)))
                           for im, kp in zip(images, keypoints, strict=True)])
    y = targets.permute(0, 2, 3, 1).reshape(-1, 25).double()
    with torch.no_grad():
        feat = net.features(x)
        prev = None
        for stage in net.stages:
            inp = feat if prev is None else torch.cat([feat, prev], 1)
            f = stage.body(inp).permute(0, 2, 3, 1).reshape(len(y), -1).double()
            f1 = torch.cat([f, torch.ones(len(f), 1, dtype=f.dtype)], 1)
            w = torch.linalg.lstsq(f1, y).solution
            stage.out.weight.copy_(w[:-1].T.float()[:, :, None, None])
            stage.out.bias.copy_(w[-1].float())
            prev = stage(inp)


def make_net(images, keypoints):
    """A tiny two-stage net: random trunk, BatchNorm statistics calibrated on the images (so
    that activations do not vanish, and BatchNorm is far from identity), fitted outputs."""
    torch.manual_seed(0)
    net = create("dope_lite_tiny", num_stages=2, head_channels=256)
    x = torch.stack([torch.from_numpy(preprocess(im, MEAN, STD)[0]) for im in images])
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.reset_running_stats()
            m.momentum = None  # cumulative average: one pass sets the batch statistics
    with torch.no_grad():
        net.train()(x)
    net.eval()
    fit_output_layers(net, images, keypoints)
    net.weights_record = WeightsRecord(
        arch="dope_lite_tiny", arch_kwargs={"num_stages": 2, "head_channels": 256},
        object_name="box", cuboid=CUBOID, input_size=(120, 160), mean=MEAN, std=STD)
    return net


@pytest.fixture(scope="module")
def source():
    return SyntheticCuboidSource(CUBOID, 3, (120, 160), options=CuboidSourceOptions(
        max_instances=2, empty_probability=0, distance_range=(2.0, 3.0)))


@pytest.fixture(scope="module")
def exported(tmp_path_factory, source):
    net = make_net([source[i].image for i in range(len(source))],
                   [source[i].keypoints for i in range(len(source))])
    path = export_onnx(net, tmp_path_factory.mktemp("onnx") / "pose.onnx")
    return net, path


def ort_session(path):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


@pytest.mark.parametrize("shape", [(2, 3, 64, 96), (1, 3, 120, 160), (3, 3, 40, 56)])
def test_maps_equal_torch_for_dynamic_batch_and_size(exported, shape):
    net, path = exported
    x = torch.randn(*shape, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        b_t, a_t = net(x)
    b_o, a_o = ort_session(path).run(None, {"image": x.numpy()})
    assert b_o.shape == tuple(b_t.shape) and a_o.shape == tuple(a_t.shape)
    np.testing.assert_allclose(b_o, b_t.numpy(), atol=1e-4, rtol=0)
    np.testing.assert_allclose(a_o, a_t.numpy(), atol=1e-4, rtol=0)


def test_record_is_embedded(exported):
    net, path = exported
    record, precision = read_onnx_record(path)
    assert precision == "fp32"
    assert record.to_dict() == net.weights_record.to_dict()
    model = onnx.load(str(path))
    onnx.checker.check_model(model)
    assert [i.name for i in model.graph.input] == ["image"]


def test_onnx_estimator_gives_the_same_poses_as_torch(exported, source):
    net, path = exported
    K = source.K
    cam = PinholeCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 160, 120)
    t_est = TorchPoseEstimator(net, cam)
    o_est = OnnxPoseEstimator(path, cam, threads=1)
    assert o_est.object_name == "box" and o_est.cuboid == CUBOID
    assert "CPUExecutionProvider" in o_est.providers
    total = 0
    for i in range(len(source)):
        image = source[i].image
        t_dets, o_dets = t_est(image), o_est(image)
        assert len(t_dets) == len(o_dets)
        total += len(t_dets)
        for a, b in zip(t_dets, o_dets, strict=True):
            # maps agree to ~1e-6: poses to 1e-5 (10 µm, 0.0006 degree), keypoints to 1e-3 px
            torch.testing.assert_close(a.pose, b.pose, atol=1e-5, rtol=0)
            torch.testing.assert_close(a.keypoints, b.keypoints, atol=1e-3, rtol=0,
                                       equal_nan=True)
            assert a.confidence == pytest.approx(b.confidence, abs=1e-5)
            assert a.num_points == b.num_points
    assert total >= len(source)  # the comparison is not vacuous: the fitted net detects


def test_spinning_threads_are_a_session_option(exported):
    """``spin``: onnxruntime's intra-op threads spin-wait or not (its session config entry);
    the maps do not change. Without it, onnxruntime's default is left alone."""
    _, path = exported
    cam = PinholeCamera(100.0, 100.0, 79.5, 59.5, 160, 120)
    x = np.random.default_rng(0).normal(size=(1, 3, 120, 160)).astype(np.float32)
    maps = {}
    for spin in (None, True, False):
        est = OnnxPoseEstimator(path, cam, threads=2, spin=spin)
        entries = est.session.get_session_options()
        key = "session.intra_op.allow_spinning"
        if spin is None:
            assert not _has_entry(entries, key)
        else:
            assert entries.get_session_config_entry(key) == ("1" if spin else "0")
        maps[spin] = est.run_network(x)
    for spin in (True, False):
        np.testing.assert_array_equal(maps[spin][0], maps[None][0])


def _has_entry(options, key: str) -> bool:
    try:
        options.get_session_config_entry(key)
    except Exception:  # onnxruntime raises when the entry was never set
        return False
    return True


def test_fp16_export(tmp_path, exported):
    net, _ = exported
    path = export_onnx(net, tmp_path / "fp16.onnx", fp16=True)
    model = onnx.load(str(path))
    conv_weights = [i for i in model.graph.initializer if len(i.dims) == 4]
    assert conv_weights and all(i.data_type == onnx.TensorProto.FLOAT16 for i in conv_weights)
    assert model.graph.input[0].type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert read_onnx_record(path)[1] == "fp16"
    x = torch.randn(1, 3, 64, 96, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        b_t, a_t = net(x)
    b_o, a_o = ort_session(path).run(None, {"image": x.numpy()})
    assert b_o.dtype == np.float32
    scale = float(np.abs(b_t.numpy()).max())
    np.testing.assert_allclose(b_o, b_t.numpy(), atol=2e-2 * scale)


def test_the_embedded_records_decoding_is_used(tmp_path, exported):
    net, _ = exported
    record = net.weights_record
    net.weights_record = dataclasses.replace(record, decode={"crop_blend_max_deg": 30.0})
    try:
        path = export_onnx(net, tmp_path / "decode.onnx")
    finally:
        net.weights_record = record
    cam = PinholeCamera(100.0, 100.0, 79.5, 59.5, 160, 120)
    assert OnnxPoseEstimator(path, cam, threads=1).decode.crop_blend_max_deg == 30.0
    assert OnnxPoseEstimator(path, cam, threads=1, decode=DecodeConfig()).decode == DecodeConfig()


def test_export_needs_a_record(tmp_path):
    with pytest.raises(ExportError, match="no weights record"):
        export_onnx(create("dope_lite_tiny"), tmp_path / "x.onnx")
    assert not (tmp_path / "x.onnx").exists()


def test_foreign_onnx_models_are_refused(tmp_path):
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])], "other",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 8, 8])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3, 8, 8])],
    )
    path = tmp_path / "other.onnx"
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=10)
    onnx.save(model, str(path))
    cam = np.eye(3)
    with pytest.raises(WeightsError, match="not an evtrack pose model"):
        OnnxPoseEstimator(path, cam, cuboid=CUBOID)
    with pytest.raises(WeightsError, match="not found"):
        OnnxPoseEstimator(tmp_path / "missing.onnx", cam)
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"garbage")
    with pytest.raises(WeightsError, match="cannot read ONNX"):
        read_onnx_record(bad)


def test_an_opset_the_exporter_cannot_write_or_a_wrong_suffix_is_refused(tmp_path, exported):
    from evtrack.models.onnx_export import MIN_OPSET

    net, _ = exported
    with pytest.raises(ExportError, match=f"opset 5: the exporter writes opset {MIN_OPSET}"):
        export_onnx(net, tmp_path / "old.onnx", opset=5)
    with pytest.raises(ExportError, match=r"model\.txt: the output must be an \.onnx file"):
        export_onnx(net, tmp_path / "model.txt")
    assert list(tmp_path.iterdir()) == []  # nothing written
