"""The shipped demo weights: loadable safely, within the size budget, documented, and locating
the demo object in held-out renders (a regression test of their quality, not the benchmark)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from evtrack.demo import DEMO_OBJECT
from evtrack.eval.pose_metrics import GROSS_MISS_M
from evtrack.models import TorchPoseEstimator, load_model
from evtrack.models.weights import list_weights, zoo_dir


def _shipped():
    found = [(p, r) for p, r in list_weights() if r.object_name == DEMO_OBJECT]
    assert found, f"no shipped weights for the demo object {DEMO_OBJECT!r} in {zoo_dir()}"
    return found[0]


def test_shipped_weights_are_safe_small_and_documented() -> None:
    path, record = _shipped()
    assert path.stat().st_size <= 10 * 2**20
    raw = torch.load(path, weights_only=True)  # plain data only
    assert raw["format"] == "evtrack.pose_weights"
    card = path.with_suffix(".md").read_text()
    for text in (record.arch, DEMO_OBJECT, "wall_time_s", "val/keypoint_recall"):
        assert text in card
    net, rec = load_model(path, object_name=DEMO_OBJECT)
    assert sum(p.numel() for p in net.parameters()) <= 5_000_000
    assert rec.training["wall_time_s"] > 0


def _renders(path, object_spec: str, n: int, seed: int) -> list:
    """``n`` renders (``SimSource`` samples) of ``object_spec`` at the training resolution of
    the weights ``path``, 0.4-0.9 m away, in random cluttered scenes of 24 renders each, with
    a seed no training run used."""
    from evtrack.train.sim_source import SimSource, SimSourceOptions

    _, record = load_model(path)
    source = SimSource(object_spec, record.cuboid, n, tuple(record.input_size),
                       object_name=record.object_name, seed=seed,
                       options=SimSourceOptions(samples_per_scene=min(n, 24), z_range=(0.4, 0.9)))
    try:
        return [source[i] for i in range(len(source))]
    finally:
        source.close()


@dataclass(frozen=True)
class HeldOut:
    """What a shipped network must do on the held-out renders: median position (m) and
    rotation (deg) errors and gross misses (detections more than 10 cm off, or none) at most
    these."""

    median_position_m: float
    median_rotation_deg: float
    gross_misses: int


# 48 renders: two cluttered scenes of 24, seed 987654. A render's last bits differ between
# machines (the rasteriser's arithmetic, the network's convolution kernels and threads), and
# a median over 24 renders moved with them across its bound. These bounds stand well outside
# the spread measured over seven inputs (AMD EPYC, 2026-12-07): scene seeds 987654, 1, 2 and
# 3 (other images altogether), and seed 987654 rendered by Mesa's softpipe rasteriser instead
# of llvmpipe, with oneDNN limited to SSE4.1 and with one thread (the last two changed the
# maps' last bits, not the poses). The worst of the seven, per network (median position cm /
# median rotation deg / gross misses of 48): coded box 1.65 / 5.07 / 4, cracker box
# 2.26 / 5.59 / 5, tomato can 3.60 / 8.41 / 4, mustard bottle 3.02 / 8.24 / 8, potted meat
# can 2.57 / 8.18 / 4. Bounds: 1.5x the worst position and 1.4x the worst rotation (rounded
# up to 0.5), three gross misses more than the worst.
HELD_OUT_SEED = 987_654
HELD_OUT_RENDERS = 48
HELD_OUT_BOUNDS = {
    "coded_box": HeldOut(0.025, 7.5, 7),
    "003_cracker_box": HeldOut(0.035, 8.0, 8),
    "005_tomato_soup_can": HeldOut(0.055, 12.0, 7),
    "006_mustard_bottle": HeldOut(0.05, 11.5, 11),
    "010_potted_meat_can": HeldOut(0.04, 11.5, 7),
}


def _held_out_errors(path, object_spec: str, n: int = HELD_OUT_RENDERS,
                     seed: int = HELD_OUT_SEED) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) errors, (n,) each, of the most confident detection on
    ``n`` renders of ``object_spec`` (a sim object or a mesh path) with a seed no training run
    used; NaN where nothing was detected."""
    from evtrack.eval.metrics import position_errors, rotation_errors

    samples = _renders(path, object_spec, n, seed)
    est = TorchPoseEstimator.from_weights(path, samples[0].K)
    found = [(est(s.image), s.poses[0]) for s in samples]
    nan = np.full((4, 4), np.nan)
    T_est = torch.as_tensor(np.stack([d[0].pose.numpy() if d else nan for d, _ in found]))
    T_true = torch.as_tensor(np.stack([truth for _, truth in found]))
    return (position_errors(T_est, T_true).numpy(),
            np.degrees(rotation_errors(T_est, T_true).numpy()))


def _check_held_out(name: str, dt: np.ndarray, dr: np.ndarray) -> None:
    """``dt`` (m), ``dr`` (deg) within the network's :data:`HELD_OUT_BOUNDS`; no detection
    counts as a gross miss."""
    bound = HELD_OUT_BOUNDS[name]
    dt, dr = np.nan_to_num(dt, nan=np.inf), np.nan_to_num(dr, nan=180.0)
    gross = int(np.sum(dt > GROSS_MISS_M))
    report = (f"{name}: median {100 * np.median(dt):.2f} cm / {np.median(dr):.2f} deg, "
              f"{gross} gross misses of {len(dt)}; errors (cm) {np.round(100 * dt, 1)}")
    assert np.median(dt) < bound.median_position_m, report
    assert np.median(dr) < bound.median_rotation_deg, report
    assert gross <= bound.gross_misses, report


def test_every_shipped_network_has_held_out_bounds() -> None:
    names = {record.object_name for _, record in list_weights()}
    assert names == set(HELD_OUT_BOUNDS), "a shipped network without bounds, or bounds without one"


def test_shipped_weights_locate_the_demo_object_in_held_out_renders() -> None:
    pytest.importorskip("moderngl")
    path, _ = _shipped()
    _check_held_out(DEMO_OBJECT, *_held_out_errors(path, DEMO_OBJECT))


def _shipped_ycb():
    """The shipped weights of YCB objects (their names start with the YCB number)."""
    return [(p, r) for p, r in list_weights() if r.object_name[:3].isdigit()]


@pytest.mark.parametrize("index", range(len(_shipped_ycb())))
def test_shipped_ycb_weights_locate_their_object_in_held_out_renders(index, ycb_dir) -> None:
    """Each shipped YCB network (trained from the coded box's weights with
    ``model.init_transfer``) finds its own object, rendered from the mesh in ../shared, in 48
    cluttered renders: median errors and gross misses within :data:`HELD_OUT_BOUNDS`. A
    network that mixes its corners up fails the rotation bound by far (one that did, after a
    short training run, measured 8.6 cm / 54 deg); one whose crop pass sinks its object below
    a distractor's detection fails the gross-miss bound."""
    pytest.importorskip("moderngl")
    path, record = _shipped_ycb()[index]
    name = record.object_name
    assert path.stat().st_size <= 10 * 2**20
    card = path.with_suffix(".md").read_text()
    assert name in card and "held-out" in card.lower()  # the card states its held-out accuracy
    mesh = ycb_dir / name / f"{name}_textured.gltf"
    _check_held_out(name, *_held_out_errors(path, str(mesh)))


def _same_pose(a, b) -> bool:
    return bool(torch.allclose(a.pose, b.pose, atol=1e-6, rtol=0)
                and a.num_points == b.num_points)


def test_onnx_and_torch_give_the_shipped_network_the_same_poses(tmp_path) -> None:
    """Issue #6: the exported model computes the network's maps to float32 rounding (within
    1e-4 of torch's; ~5e-6 measured), and the decoded poses are the same: at least 90 % of
    the detections identical to 1e-6 (matched by pose, not by rank, since two detections of
    near-equal confidence may swap). Before keypoints went to PnP on a grid
    (``PNP_GRID_PX``), RANSAC turned the maps' last-bit differences into poses 1-2 degrees
    apart on a third of frames. Every threshold of the decoding (a keypoint on a grid line,
    RANSAC's inlier distance, the search's trigger) can still flip where the two backends'
    maps straddle it, and where that happens depends on the render's own last bits: 1 of ~60
    detections on renders of three seeds with llvmpipe's default, bilinear-LOD
    (``GALLIVM_PERF=brilinear``) and approximate-rho sampling, and softpipe's."""
    pytest.importorskip("moderngl")
    pytest.importorskip("onnxruntime")
    from evtrack.models import OnnxPoseEstimator
    from evtrack.models.onnx_export import export_onnx

    path, _ = _shipped()
    net, _ = load_model(path)
    onnx_path = export_onnx(net, tmp_path / "demo.onnx")
    samples = _renders(path, DEMO_OBJECT, 24, seed=4321)
    t_est = TorchPoseEstimator.from_weights(path, samples[0].K)
    o_est = OnnxPoseEstimator(onnx_path, samples[0].K, threads=1)
    assert t_est.decode.ransac and t_est.decode.crop_refine > 0
    detections = identical = 0
    for s in samples:
        for torch_maps, onnx_maps in zip(t_est.predict_maps([s.image])[:2],
                                         o_est.predict_maps([s.image])[:2], strict=True):
            np.testing.assert_allclose(onnx_maps, torch_maps, rtol=0, atol=1e-4)
        a, b = t_est(s.image), o_est(s.image)
        detections += max(len(a), len(b))
        unmatched = list(b)
        for da in a:
            match = next((db for db in unmatched if _same_pose(da, db)), None)
            if match is not None:
                unmatched.remove(match)
                identical += 1
    assert detections >= 20  # the network finds the object in (nearly) every render
    assert identical >= 0.9 * detections, f"{identical} of {detections} detections identical"
