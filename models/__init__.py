"""Pose networks, their registry, keypoint decoding + PnP, and the ONNX runtime estimator.

Example::

    from evtrack.models import create, list_models, TorchPoseEstimator, export_onnx
    net = create("dope_lite_base", weights="path/to/weights.pt")   # or weights="default"
    estimator = TorchPoseEstimator(net, camera)                    # camera: PinholeCamera
    for det in estimator(rgb):                                     # rgb: uint8 (H, W, 3)
        det.pose, det.confidence, det.keypoints                    # (4,4) object->camera, ...
    export_onnx(net, "pose.onnx")
    onnx_estimator = OnnxPoseEstimator("pose.onnx", camera)        # same interface
    refiner = DepthRefiner.from_mesh("object.glb")                  # RGB-D: ICP on the depth
    poses = refiner.refine_detections(estimator(rgb), depth, camera.K())
    appearance = AppearanceRefiner(load_mesh("object.glb", recenter=False), camera)
    result = appearance.refine(predicted_pose, rgb)                # render-and-compare
"""

from __future__ import annotations

from evtrack.models import dope_lite  # noqa: F401  (registers the DOPE-Lite models)
from evtrack.models._registry import is_model, list_models, model_entrypoint, register_model
from evtrack.models.appearance_refine import (
    AppearanceRefineConfig,
    AppearanceRefiner,
    AppearanceResult,
)
from evtrack.models.averaging import average_weights
from evtrack.models.cuboid import CENTROID_INDEX, NUM_KEYPOINTS, Cuboid
from evtrack.models.decode import (
    DecodeConfig,
    InstanceKeypoints,
    PoseDetection,
    decode_poses,
    extract_instances,
    solve_pose,
)
from evtrack.models.depth_refine import DepthRefineConfig, DepthRefiner, RefineResult
from evtrack.models.depth_regions import DepthRegion, RegionConfig, object_regions
from evtrack.models.dope_lite import DopeLite, DopeLiteConfig
from evtrack.models.estimator import PoseEstimator, TorchPoseEstimator, preprocess
from evtrack.models.factory import create, load_model
from evtrack.models.fold_batchnorm import fold_batchnorm
from evtrack.models.keypoints import find_peaks, grid_to_pixel, pixel_to_grid
from evtrack.models.mesh_registration import (
    Registration,
    RegistrationConfig,
    find_mesh,
    register_mesh,
)
from evtrack.models.onnx_estimator import OnnxPoseEstimator
from evtrack.models.onnx_export import ExportError, export_onnx, read_onnx_record
from evtrack.models.summary import count_flops, count_parameters
from evtrack.models.weights import (
    WeightsError,
    WeightsRecord,
    find_default_weights,
    list_weights,
    load_weights_file,
    model_card,
    read_record,
    save_weights,
    set_record_decode,
    write_model_card,
)

__all__ = [
    "AppearanceRefineConfig",
    "AppearanceRefiner",
    "AppearanceResult",
    "CENTROID_INDEX",
    "NUM_KEYPOINTS",
    "Cuboid",
    "DecodeConfig",
    "DepthRefineConfig",
    "DepthRefiner",
    "DepthRegion",
    "DopeLite",
    "DopeLiteConfig",
    "ExportError",
    "InstanceKeypoints",
    "OnnxPoseEstimator",
    "PoseDetection",
    "PoseEstimator",
    "RefineResult",
    "RegionConfig",
    "Registration",
    "RegistrationConfig",
    "TorchPoseEstimator",
    "WeightsError",
    "WeightsRecord",
    "average_weights",
    "count_flops",
    "count_parameters",
    "create",
    "decode_poses",
    "export_onnx",
    "extract_instances",
    "find_default_weights",
    "find_mesh",
    "find_peaks",
    "fold_batchnorm",
    "grid_to_pixel",
    "is_model",
    "list_models",
    "list_weights",
    "load_model",
    "load_weights_file",
    "model_card",
    "model_entrypoint",
    "object_regions",
    "pixel_to_grid",
    "preprocess",
    "read_onnx_record",
    "read_record",
    "register_mesh",
    "register_mesh",
    "register_model",
    "save_weights",
    "set_record_decode",
    "solve_pose",
    "write_model_card",
]
