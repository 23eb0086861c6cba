"""Export one predict+update step of each filter to ONNX and run it in onnxruntime.

A filter's state travels as explicit inputs and outputs (ONNX graphs are stateless), so a
runtime calls the graph once per step and feeds the outputs back. The batch size B and the
number of RoIs N are dynamic. Shapes and dtypes of the inputs, in order:

* ``VelocityKF``: ``twist (B,6)``, ``cov (B,6,6)``, ``reference (B,6)``, ``dt (B,)`` s,
  ``uv (B,N,2)`` ideal pinhole px, ``depth (B,N)`` m, ``flow (B,N,2)`` px/s,
  ``normal_only (B,N)`` bool, ``mask (B,N)`` bool -> ``twist``, ``cov``, ``skipped (B,2)``
  (the next ``reference`` is the output ``twist``).
* ``PoseUKF``: ``t (B,3)``, ``q (B,4)``, ``cov (B,6,6)``, ``initialized (B,)`` bool,
  ``rejected_run (B,)`` int64, ``twist (B,6)``, ``dt (B,)``, ``t_meas (B,3)``, ``q_meas (B,4)``,
  ``cov_meas (B,6,6)``, ``valid (B,)`` bool -> ``t, q, cov, initialized, rejected_run, used,
  rejected, reinitialised``. With a velocity bias (``config.velocity_bias``): ``cov (B,9,9)``
  and a last input ``bias (B,3)`` (m/s per m/s of the object's speed), and a last output,
  the new ``bias``.
* ``PoseTwistUKF``: as ``PoseUKF`` with ``twist (B,6)`` after ``q`` in the state and no twist
  input -> ``t, q, twist, cov, initialized, rejected_run, used, rejected, reinitialised``.

The float dtype is the filter's (float64 by default; ``.to(torch.float32)`` first for a float32
graph). The graphs use the unrolled linear algebra of :mod:`linalg` (ONNX has no Cholesky),
and keep every scalar constant as a tensor of the filter's dtype (the dynamo exporter would
store Python floats as float32).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from evtrack.filters.interaction import interaction_matrix
from evtrack.filters.pose_ukf import PoseTwistUKF, PoseUKF
from evtrack.filters.velocity_kf import VelocityKF
from evtrack.utils import atomic_path

__all__ = [
    "DEFAULT_OPSET",
    "FilterStep",
    "step_inputs",
    "export_step",
    "run_onnx",
]

DEFAULT_OPSET = 18

# A pose filter's measurement inputs and its outputs after the state's.
_POSE_MEAS = ("t_meas", "q_meas", "cov_meas", "valid")
_POSE_FLAGS = ("initialized_out", "rejected_run_out", "used", "rejected", "reinitialised")
_NAMES: dict[type, tuple[tuple[str, ...], tuple[str, ...]]] = {
    VelocityKF: (
        ("twist", "cov", "reference", "dt", "uv", "depth", "flow", "normal_only", "mask"),
        ("twist_out", "cov_out", "skipped"),
    ),
    PoseUKF: (
        ("t", "q", "cov", "initialized", "rejected_run", "twist", "dt", *_POSE_MEAS),
        ("t_out", "q_out", "cov_out", *_POSE_FLAGS),
    ),
    PoseTwistUKF: (
        ("t", "q", "twist", "cov", "initialized", "rejected_run", "dt", *_POSE_MEAS),
        ("t_out", "q_out", "twist_out", "cov_out", *_POSE_FLAGS),
    ),
}
# Inputs whose second dimension is the number of RoIs (VelocityKF only).
_ROI_INPUTS = {"uv", "depth", "flow", "normal_only", "mask"}


class FilterStep(nn.Module):
    """A stateless module around a filter's pure ``step`` (what gets exported)."""

    def __init__(self, filt: VelocityKF | PoseUKF | PoseTwistUKF) -> None:
        super().__init__()
        if type(filt) not in _NAMES:
            raise TypeError(f"no ONNX step for {type(filt).__name__}")
        self.filt = filt

    @property
    def input_names(self) -> tuple[str, ...]:
        return _NAMES[type(self.filt)][0] + (("bias",) if _has_bias(self.filt) else ())

    @property
    def output_names(self) -> tuple[str, ...]:
        return _NAMES[type(self.filt)][1] + (("bias_out",) if _has_bias(self.filt) else ())

    def forward(self, *inputs: Tensor) -> tuple[Tensor, ...]:
        return tuple(self.filt.step(*inputs))


def _has_bias(filt: nn.Module) -> bool:
    """Whether ``filt`` is a :class:`PoseUKF` with a velocity bias in its state."""
    return isinstance(filt, PoseUKF) and filt.config.velocity_bias


def step_inputs(
    filt: VelocityKF | PoseUKF | PoseTwistUKF, batch: int = 3, rois: int = 7, seed: int = 0
) -> tuple[Tensor, ...]:
    """Plausible random inputs for one step (in ``FilterStep.input_names`` order).

    Args:
        filt: the filter (its dtype and device are used).
        batch: B. rois: N (VelocityKF only).
        seed: seed of the generator (the same seed gives the same inputs).
    """
    g = torch.Generator().manual_seed(seed)
    dtype, device = filt.cov.dtype, filt.cov.device

    def rnd(*shape: int, scale: float = 1.0) -> Tensor:
        return (torch.randn(*shape, generator=g, dtype=torch.float64) * scale).to(dtype)

    def spd(n: int, scale: float) -> Tensor:
        a = rnd(batch, n, n, scale=0.3)
        return (a @ a.transpose(-1, -2) + torch.eye(n, dtype=dtype)) * scale

    dt = torch.full((batch,), 1e-3, dtype=dtype)
    B = torch.ones(batch, dtype=torch.bool)
    if isinstance(filt, VelocityKF):
        # RoIs over the image seeing a rigid motion, half of them normal-only, some padding.
        size = torch.tensor([2 * filt.principal[0].item(), 2 * filt.principal[1].item()])
        uv = (torch.rand(batch, rois, 2, generator=g, dtype=torch.float64) * size).to(dtype)
        depth = torch.rand(batch, rois, generator=g, dtype=torch.float64).to(dtype) + 0.5
        depth[0, 0] = torch.nan  # a RoI without depth, skipped and counted
        twist = rnd(batch, 6, scale=0.5)
        J = interaction_matrix(uv, depth, filt.camera)
        flow = torch.nan_to_num((J @ twist[:, None, :, None]).squeeze(-1)) + rnd(
            batch, rois, 2, scale=5.0
        )
        normal = torch.rand(batch, rois, generator=g) < 0.5
        edge = rnd(batch, rois, 2)
        edge = edge / edge.norm(dim=-1, keepdim=True)
        flow = torch.where(normal[..., None], (flow * edge).sum(-1, keepdim=True) * edge, flow)
        mask = torch.rand(batch, rois, generator=g) < 0.9
        cov = torch.diag_embed(filt.init_var).expand(batch, 6, 6).to(dtype)
        out = (twist, cov, twist * 0.9, dt, uv, depth, flow, normal, mask)
    else:
        t = rnd(batch, 3, scale=0.2) + torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
        q = rnd(batch, 4)
        q = q / q.norm(dim=-1, keepdim=True)
        t_meas = t + rnd(batch, 3, scale=0.01)
        q_meas = q + rnd(batch, 4, scale=0.01)
        init = B.clone()
        init[0] = False  # a fresh track: the pose initialises it
        run = torch.tensor([0] + [4] * (batch - 1), dtype=torch.int64)
        cov_meas = spd(6, 1e-3)
        if isinstance(filt, PoseTwistUKF):
            out = (t, q, rnd(batch, 6), spd(12, 0.01), init, run, dt, t_meas, q_meas, cov_meas, B)
        elif _has_bias(filt):
            out = (t, q, spd(9, 0.01), init, run, rnd(batch, 6), dt, t_meas, q_meas, cov_meas, B,
                   rnd(batch, 3, scale=0.05))
        else:
            out = (t, q, spd(6, 0.01), init, run, rnd(batch, 6), dt, t_meas, q_meas, cov_meas, B)
    return tuple(x.to(device) for x in out)


def export_step(
    filt: VelocityKF | PoseUKF | PoseTwistUKF,
    path: str | Path,
    opset: int = DEFAULT_OPSET,
    exporter: str = "torchscript",
) -> Path:
    """Export one predict+update step of ``filt`` to ``path`` (written atomically).

    The batch size (and the number of RoIs) are dynamic. ``exporter`` picks torch's
    TorchScript-based exporter (default: the same graph as the other in 0.5 s instead of
    20-45 s) or the ``"dynamo"`` one (``torch.export`` + onnxscript). Returns the path.

    Raises:
        RuntimeError: if the graph came out with a static batch dimension.
    """
    if exporter not in ("torchscript", "dynamo"):
        raise ValueError(f"exporter must be 'torchscript' or 'dynamo', got {exporter!r}")
    step = FilterStep(filt).eval()
    example = step_inputs(filt)
    names, outputs = list(step.input_names), list(step.output_names)
    path = Path(path)
    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if exporter == "dynamo":
            batch = torch.export.Dim("batch", min=1)
            rois = torch.export.Dim("rois", min=1)
            dynamic = tuple({0: batch, 1: rois} if n in _ROI_INPUTS else {0: batch} for n in names)
            program = torch.onnx.export(
                step,
                example,
                dynamo=True,
                dynamic_shapes=(dynamic,),
                input_names=names,
                output_names=outputs,
                opset_version=opset,
                verbose=False,
            )
            program.save(str(tmp), external_data=False)
        else:
            axes = {n: {0: "batch", 1: "rois"} if n in _ROI_INPUTS else {0: "batch"} for n in names}
            axes.update({n: {0: "batch"} for n in outputs})
            torch.onnx.export(
                step,
                example,
                str(tmp),
                dynamo=False,
                input_names=names,
                output_names=outputs,
                dynamic_axes=axes,
                opset_version=opset,
            )
        _check_dynamic(tmp, step.input_names)
    return path


def _check_dynamic(path: Path, names: tuple[str, ...]) -> None:
    """Fail if the exporter fell back to static shapes (it does so with a mere warning)."""
    import onnx

    graph = onnx.load(str(path), load_external_data=False).graph
    for inp in graph.input:
        first = inp.type.tensor_type.shape.dim[0]
        if not first.dim_param:
            raise RuntimeError(
                f"ONNX export of {names}: input {inp.name!r} lost its dynamic batch "
                f"dimension (static {first.dim_value}); the step specialises on it"
            )


def run_onnx(path: str | Path, inputs: tuple[Tensor, ...] | list[Tensor]) -> list[np.ndarray]:
    """Run an exported step in onnxruntime (CPU) on inputs in the graph's input order."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    if len(names) != len(inputs):
        raise ValueError(f"{path}: the graph takes {len(names)} inputs {names}, got {len(inputs)}")
    feed = {n: x.detach().cpu().numpy() for n, x in zip(names, inputs, strict=True)}
    return session.run(None, feed)
