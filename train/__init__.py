"""Lightning training of the pose network on synthetic images.

Example::

    from evtrack.train import TrainConfig, run_training
    cfg = TrainConfig.from_yaml("configs/pose_demo_box.yaml", ["trainer.max_epochs=2"])
    result = run_training(cfg)          # result.weights: a file evtrack.models.create loads

or ``evtrack train --config configs/pose_demo_box.yaml``.
"""

from __future__ import annotations

from evtrack.train.augment import (
    AugmentConfig,
    ColorJitter,
    Compose,
    GaussianNoise,
    MotionBlur,
    RandomCrop,
    RandomOcclusion,
    RandomScale,
)
from evtrack.train.config import DataConfig, ModelConfig, ObjectConfig, TrainConfig
from evtrack.train.cuboid_source import (
    CuboidSourceOptions,
    SyntheticCuboidSource,
    draw_textured_cuboid,
)
from evtrack.train.data import EpochSampler, PoseDataModule, PoseDataset
from evtrack.train.fit import TrainResult, build_module, run_training
from evtrack.train.module import (
    LossConfig,
    OptimConfig,
    PoseLightningModule,
    corner_identity_hits,
    corner_identity_loss,
    keypoint_metrics,
)
from evtrack.train.samples import (
    PoseSample,
    SampleSource,
    SourceSpec,
    build_source,
    list_sources,
    project_keypoints,
    register_source,
)
from evtrack.train.shards import ShardError, ShardSource, write_shards
from evtrack.train.targets import TargetConfig, make_targets

__all__ = [
    "AugmentConfig",
    "ColorJitter",
    "Compose",
    "CuboidSourceOptions",
    "DataConfig",
    "EpochSampler",
    "GaussianNoise",
    "LossConfig",
    "corner_identity_hits",
    "corner_identity_loss",
    "ModelConfig",
    "MotionBlur",
    "ObjectConfig",
    "OptimConfig",
    "PoseDataModule",
    "PoseDataset",
    "PoseLightningModule",
    "PoseSample",
    "RandomOcclusion",
    "RandomCrop",
    "RandomScale",
    "SampleSource",
    "ShardError",
    "ShardSource",
    "SourceSpec",
    "SyntheticCuboidSource",
    "TargetConfig",
    "TrainConfig",
    "TrainResult",
    "build_module",
    "build_source",
    "draw_textured_cuboid",
    "keypoint_metrics",
    "list_sources",
    "make_targets",
    "project_keypoints",
    "register_source",
    "run_training",
    "write_shards",
]
