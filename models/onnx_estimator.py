"""``OnnxPoseEstimator``: the :class:`PoseEstimator` on onnxruntime (CPU, CUDA when present)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from evtrack.camera import PinholeCamera
from evtrack.models.cuboid import Cuboid
from evtrack.models.estimator import PoseEstimator, _record_kwargs
from evtrack.models.onnx_export import INPUT_NAME, OUTPUT_NAMES, read_onnx_record
from evtrack.models.weights import WeightsError

__all__ = ["OnnxPoseEstimator", "default_providers"]


def default_providers() -> list[str]:
    """CUDA first when this onnxruntime build has it, then CPU."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


class OnnxPoseEstimator(PoseEstimator):
    """Pose estimation with a model written by :func:`evtrack.models.export_onnx`.

    Args:
        path: the ``.onnx`` file (its embedded record gives cuboid, object and normalisation).
        camera: see :class:`PoseEstimator`.
        providers: onnxruntime execution providers (default: :func:`default_providers`).
        threads: intra-op threads for the CPU provider (default: onnxruntime's choice).
        spin: whether onnxruntime's intra-op threads spin-wait for work after a call
            (``session.intra_op.allow_spinning``). ``None`` (default): onnxruntime's default
            (they spin), the fastest for back-to-back calls; ``False`` for a network that
            shares the CPU with other work, such as the tracker's, at 5 Hz: spinning threads
            take the cores from it between the calls.
        cuboid, object_name: override (or supply, for a model without a record).
        input_scale: resize factor before the network; ``None`` (default): the network's
            training resolution (:func:`~evtrack.models.estimator.training_input_scale`).
        **kwargs: ``decode`` as in :class:`PoseEstimator`; default: the embedded record's
            (``WeightsRecord.decode``, else the library's defaults).
    """

    def __init__(
        self,
        path: str | Path,
        camera: PinholeCamera | np.ndarray,
        *,
        providers: Sequence[str] | None = None,
        threads: int | None = None,
        spin: bool | None = None,
        cuboid: Cuboid | None = None,
        object_name: str | None = None,
        input_scale: float | None = None,
        **kwargs,
    ) -> None:
        import onnxruntime as ort

        self.path = Path(path)
        record, self.precision = read_onnx_record(self.path)
        decode = kwargs.pop("decode", None)
        super().__init__(camera, **_record_kwargs(record, cuboid, object_name, camera,
                                                  input_scale, decode), **kwargs)
        self.record = record
        options = ort.SessionOptions()
        if threads is not None:
            options.intra_op_num_threads = int(threads)
            options.inter_op_num_threads = 1
        if spin is not None:
            options.add_session_config_entry("session.intra_op.allow_spinning",
                                             "1" if spin else "0")
        try:
            self.session = ort.InferenceSession(
                str(self.path), options, providers=list(providers or default_providers())
            )
        except Exception as exc:  # onnxruntime raises its own exception types
            raise WeightsError(self.path, f"onnxruntime cannot load the model: {exc}") from exc
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        if inputs != [INPUT_NAME] or outputs != list(OUTPUT_NAMES):
            raise WeightsError(
                self.path, f"expected input {INPUT_NAME!r} and outputs {list(OUTPUT_NAMES)}, "
                           f"found {inputs} and {outputs} (not an evtrack pose model?)"
            )

    @property
    def providers(self) -> list[str]:
        """The execution providers the session actually uses."""
        return self.session.get_providers()

    def run_network(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        belief, affinity = self.session.run(
            list(OUTPUT_NAMES), {INPUT_NAME: np.ascontiguousarray(batch, dtype=np.float32)}
        )
        return belief, affinity
