"""One predict+update step of each filter exported to ONNX equals the torch step in
onnxruntime, with batch sizes and RoI counts other than the export's."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from evtrack.camera import PinholeCamera
from evtrack.filters import PoseTwistUKF, PoseUKF, PoseUKFConfig, VelocityKF
from evtrack.filters.onnx_export import FilterStep, export_step, run_onnx, step_inputs

CAM = PinholeCamera(500.0, 480.0, 330.0, 250.0, 640, 480)
TOL = {torch.float64: 1e-9, torch.float32: 1e-5}


def _make(kind: str, dtype: torch.dtype) -> VelocityKF | PoseUKF | PoseTwistUKF:
    filt = {
        "velocity": lambda: VelocityKF(CAM, 2),
        "pose": lambda: PoseUKF(2),
        "pose_bias": lambda: PoseUKF(2, PoseUKFConfig(velocity_bias=True)),
        "pose_twist": lambda: PoseTwistUKF(2),
    }[kind]()
    return filt.to(dtype)


def _compare(filt, path: Path, batch: int, rois: int, seed: int, tol: float) -> None:
    inputs = step_inputs(filt, batch, rois, seed)
    expected = FilterStep(filt)(*inputs)
    got = run_onnx(path, inputs)
    assert len(got) == len(expected)
    for name, e, o in zip(FilterStep(filt).output_names, expected, got, strict=True):
        e = e.detach().cpu().numpy()
        assert o.shape == e.shape and o.dtype == e.dtype, name
        if e.dtype.kind in "bi":
            np.testing.assert_array_equal(o, e, err_msg=name)
        else:
            err = np.abs(o - e).max() / max(np.abs(e).max(), 1e-300)
            assert err <= tol, f"{name}: relative error {err:.2e} > {tol:.0e}"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("kind", ["velocity", "pose", "pose_bias", "pose_twist"])
def test_exported_step_equals_torch(kind: str, dtype: torch.dtype, tmp_path: Path) -> None:
    filt = _make(kind, dtype)
    path = export_step(filt, tmp_path / f"{kind}.onnx")
    # The export used B=3 (and N=7); other sizes must run too.
    for batch, rois, seed in [(5, 40, 1), (1, 1, 2), (2, 400, 3)]:
        _compare(filt, path, batch, rois, seed, TOL[dtype])


def test_feeding_outputs_back_runs_the_filter(tmp_path: Path) -> None:
    ukf = PoseUKF(4)
    path = export_step(ukf, tmp_path / "pose.onnx")
    inputs = list(step_inputs(ukf, batch=4, seed=5))
    torch_state = inputs[:5]
    for k in range(5):
        inputs[7] = inputs[7] + 0.01 * k  # the pose measurement drifts
        out_torch = FilterStep(ukf)(*torch_state, *inputs[5:])
        out_onnx = run_onnx(path, [*inputs[:5], *inputs[5:]])
        inputs[:5] = [torch.as_tensor(x) for x in out_onnx[:5]]
        torch_state = list(out_torch[:5])
    for a, b in zip(torch_state, inputs[:5], strict=True):
        np.testing.assert_allclose(
            b.numpy().astype(np.float64), a.numpy().astype(np.float64), rtol=1e-9, atol=1e-12
        )


@pytest.mark.slow
def test_dynamo_exporter_gives_the_same_graph(tmp_path: Path) -> None:
    ukf = PoseUKF(2)
    path = export_step(ukf, tmp_path / "pose_dynamo.onnx", exporter="dynamo")
    _compare(ukf, path, 5, 1, 1, 1e-9)


def test_bad_requests() -> None:
    with pytest.raises(ValueError, match="exporter"):
        export_step(PoseUKF(1), "unused.onnx", exporter="tflite")
    with pytest.raises(TypeError, match="no ONNX step"):
        FilterStep(torch.nn.Linear(1, 1))  # type: ignore[arg-type]
    assert not Path("unused.onnx").exists()
