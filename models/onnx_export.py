"""Export a pose network to ONNX (dynamic batch and image size, FP32 or FP16).

The graph has one input ``image`` (float32 ``(B, 3, H, W)``, normalised as the record says,
``H`` and ``W`` multiples of 8) and two outputs ``belief`` (``(B, 9, H/8, W/8)``) and
``affinity`` (``(B, 16, H/8, W/8)``), float32 in both precisions: an FP16 export computes in
half precision inside the graph and casts at its boundary, so callers never change. The weights
record is stored as JSON in the model's metadata (key ``evtrack.record``), which is how
:class:`~evtrack.models.onnx_estimator.OnnxPoseEstimator` knows the object, its cuboid and the
normalisation.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import torch
from torch import Tensor, nn

from evtrack.errors import EvtrackError
from evtrack.models.weights import WeightsRecord
from evtrack.utils import atomic_path

__all__ = [
    "export_onnx",
    "read_onnx_record",
    "ExportError",
    "INPUT_NAME",
    "OUTPUT_NAMES",
    "RECORD_KEY",
    "PRECISION_KEY",
    "DEFAULT_OPSET",
]

INPUT_NAME = "image"
OUTPUT_NAMES = ("belief", "affinity")
RECORD_KEY = "evtrack.record"
PRECISION_KEY = "evtrack.precision"
DEFAULT_OPSET = 18
MIN_OPSET = 18
"""The oldest opset torch's exporter (``dynamo=True``) writes; below it the export fails."""
_TRACE_SIZE = (64, 96)  # (H, W) of the example input used for tracing; any multiple of 8


class ExportError(EvtrackError, RuntimeError):
    """The ONNX exporter failed on a network."""


class _Fp16Boundary(nn.Module):
    """Runs ``net`` in half precision with float32 input and outputs."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net.half()

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        belief, affinity = self.net(x.half())
        return belief.float(), affinity.float()


def export_onnx(
    net: nn.Module,
    path: str | Path,
    *,
    record: WeightsRecord | None = None,
    fp16: bool = False,
    opset: int = DEFAULT_OPSET,
) -> Path:
    """Export ``net`` to the ONNX file ``path`` (written atomically, one self-contained file).

    Args:
        net: a pose network (its ``weights_record`` is used when ``record`` is ``None``).
        path: output ``.onnx`` file.
        record: the weights record to embed; required if the network has none.
        fp16: compute in half precision (weights stored as float16); inputs/outputs stay float32.
        opset: ONNX opset version (>= :data:`MIN_OPSET`).

    Raises:
        ExportError: when the network has no record, the path is no ``.onnx`` file, the opset
            is below :data:`MIN_OPSET`, or the exporter fails or writes another opset (nothing
            is written then).
    """
    import copy

    import onnx

    record = record or getattr(net, "weights_record", None)
    if record is None:
        raise ExportError("the network has no weights record; load weights first or pass record=")
    if Path(path).suffix.lower() != ".onnx":
        raise ExportError(f"{path}: the output must be an .onnx file")
    if int(opset) < MIN_OPSET:
        raise ExportError(f"opset {opset}: the exporter writes opset {MIN_OPSET} or later")
    model = copy.deepcopy(net).cpu().float().eval()
    if fp16:
        model = _Fp16Boundary(model).eval()
    example = torch.zeros(1, 3, *_TRACE_SIZE)
    dims = {
        0: torch.export.Dim("batch", min=1),
        2: torch.export.Dim("height", min=8),
        3: torch.export.Dim("width", min=8),
    }
    path = Path(path)
    log = io.StringIO()
    with atomic_path(path) as tmp:
        try:
            with contextlib.redirect_stdout(log):
                torch.onnx.export(
                    model, (example,), str(tmp), input_names=[INPUT_NAME],
                    output_names=list(OUTPUT_NAMES), dynamic_shapes={"x": dims},
                    opset_version=opset, dynamo=True, external_data=False,
                )
        except Exception as exc:
            raise ExportError(f"ONNX export of {type(net).__name__} failed: {exc}\n"
                              f"{log.getvalue()[-2000:]}") from exc
        proto = onnx.load(str(tmp))
        written = next((o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")),
                       None)
        if written != int(opset):
            raise ExportError(f"asked for opset {opset}, the exporter wrote opset {written}: "
                              f"nothing written\n{log.getvalue()[-2000:]}")
        meta = {RECORD_KEY: json.dumps(record.to_dict()), PRECISION_KEY: "fp16" if fp16 else "fp32"}
        del proto.metadata_props[:]
        for key, value in meta.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.checker.check_model(proto)
        onnx.save(proto, str(tmp))
    return path


def read_onnx_record(path: str | Path) -> tuple[WeightsRecord | None, str]:
    """The weights record and precision (``"fp32"``/``"fp16"``) stored in an exported model."""
    import onnx

    from evtrack.models.weights import WeightsError

    path = Path(path)
    if not path.is_file():
        raise WeightsError(path, "ONNX file not found")
    try:
        proto = onnx.load(str(path), load_external_data=False)
    except Exception as exc:
        raise WeightsError(path, f"cannot read ONNX model: {exc}") from exc
    meta = {p.key: p.value for p in proto.metadata_props}
    record = None
    if RECORD_KEY in meta:
        try:
            data = json.loads(meta[RECORD_KEY])
        except json.JSONDecodeError as exc:
            raise WeightsError(path, f"corrupt {RECORD_KEY} metadata: {exc}") from exc
        record = WeightsRecord.from_dict(data, f"{path}: {RECORD_KEY}")
    return record, meta.get(PRECISION_KEY, "fp32")
