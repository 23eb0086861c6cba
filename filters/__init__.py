"""Filters: the interaction matrix, the 6-DoF velocity Kalman filter and the pose UKFs.

Method: sections III-B and III-C of the paper (arXiv 2508.14776), with the conventions of
``docs/architecture.md``: twists ``[v_o, ω]`` in the camera frame with ``Ṗ = v_o + ω × P``,
optical flow in px/s, quaternions wxyz, float64 by default.

    J = interaction_matrix(uv, depth, camera)        # (N,2,6): twist -> px/s
    kf = VelocityKF(camera, batch_size=B)            # flows -> twist, every ~1 ms
    twist = kf(dt, uv, depth, flow, normal_only, mask)
    ukf = PoseUKF(batch_size=B)                      # twist + low-rate poses -> pose
    ukf.predict(twist, dt); ukf.update(t_meas, q_meas, cov_meas)
    cv = PoseTwistUKF(batch_size=B)                  # constant-velocity variant (as ROFT)

Each filter also has a pure ``step`` (state in, state out) that exports to ONNX
(:mod:`evtrack.filters.onnx_export`), and ``compile_steps()`` to run its steps through
``torch.compile`` (batch-1 latency is otherwise bound by per-op dispatch). The torch steps are
the specification; one float64 CPU track runs on a single-track backend instead (NumPy, or
numba where installed: :mod:`evtrack.filters.backends`), equal to them to rounding.
"""

from evtrack.filters.config import (
    PoseTwistUKFConfig,
    PoseUKFConfig,
    VelocityKFConfig,
    load_filters_config,
)
from evtrack.filters.interaction import interaction_matrix, undistort_flow
from evtrack.filters.onnx_export import export_step, run_onnx
from evtrack.filters.pose_ukf import PoseTwistUKF, PoseUKF
from evtrack.filters.velocity_kf import VelocityKF
from evtrack.filters.weighting import laplacian_weights

__all__ = [
    "PoseTwistUKF",
    "PoseTwistUKFConfig",
    "PoseUKF",
    "PoseUKFConfig",
    "VelocityKF",
    "VelocityKFConfig",
    "export_step",
    "interaction_matrix",
    "laplacian_weights",
    "load_filters_config",
    "run_onnx",
    "undistort_flow",
]
