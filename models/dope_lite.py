"""DOPE-Lite: DOPE's outputs (belief maps + affinity fields, stride 8) from a compact trunk.

DOPE (Tremblay et al., CoRL 2018) predicts, at 1/8 of the input resolution, 9 *belief maps*
(one per projected cuboid corner, plus the projected centroid) and 16 *affinity fields* (for
each corner, the 2-D unit vector pointing from that corner to the object's centroid). Its VGG-19
trunk and six 7x7 refinement stages cost tens of GFLOPs. DOPE-Lite keeps the outputs and swaps
the network for one meant for embedded GPUs and CPUs:

* a MobileNet-style trunk of depthwise-separable blocks down to stride 32,
* a light top-down path (nearest upsampling + lateral 1x1 convolutions) back to stride 8, so
  every output cell sees a wide context at little cost,
* a first head and optional refinement stages; each refinement stage reads the shared features
  concatenated with the previous stage's maps, as in DOPE, and uses dilated depthwise
  convolutions for reach.

Output cell ``(i, j)`` covers the input pixels ``[8j, 8j+8) x [8i, 8i+8)``; its centre is the
pixel ``(8j + 3.5, 8i + 3.5)`` (see :mod:`evtrack.models.keypoints`). Inputs must be float32
images ``(B, 3, H, W)`` normalised with the weights record's mean/std; ``H`` and ``W`` must be
multiples of 8 (the estimators pad to that).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from evtrack.errors import ConfigError
from evtrack.models._registry import register_model

__all__ = [
    "DopeLite",
    "DopeLiteConfig",
    "NUM_BELIEF",
    "NUM_AFFINITY",
    "OUTPUT_STRIDE",
    "dope_lite_tiny",
    "dope_lite_small",
    "dope_lite_base",
    "dope_lite_large",
]

NUM_BELIEF = 9  # 8 cuboid corners + centroid
NUM_AFFINITY = 16  # (dx, dy) from each of the 8 corners to the centroid
OUTPUT_STRIDE = 8


@dataclass(frozen=True)
class DopeLiteConfig:
    """Hyper-parameters of :class:`DopeLite`.

    Attributes:
        stem_channels: channels of the stride-2 3x3 stem convolution.
        channels: channels at strides 4, 8, 16 and 32.
        depths: depthwise-separable blocks per level (the first one of each level downsamples).
        fpn_channels: channels of the top-down path and of the stride-8 features.
        head_channels: channels inside each stage head.
        head_blocks: depthwise-separable blocks in each stage head.
        num_stages: 1 = a single head; k > 1 adds k-1 refinement stages (DOPE uses 6).
        refine_dilations: dilation of each block in a refinement stage (its length sets the
            number of blocks); 1 = ordinary 3x3.
    """

    stem_channels: int = 16
    channels: tuple[int, int, int, int] = (32, 64, 160, 320)
    depths: tuple[int, int, int, int] = (2, 3, 4, 4)
    fpn_channels: int = 96
    head_channels: int = 96
    head_blocks: int = 2
    num_stages: int = 2
    refine_dilations: tuple[int, ...] = (1, 2, 4)

    def __post_init__(self) -> None:
        if len(self.channels) != 4 or len(self.depths) != 4:
            raise ValueError("channels and depths need one entry per stride 4, 8, 16, 32")
        if min(self.depths) < 1:
            raise ValueError(f"every level needs at least one block, got depths={self.depths}")
        if self.num_stages < 1:
            raise ValueError(f"num_stages must be >= 1, got {self.num_stages}")
        if not self.refine_dilations or min(self.refine_dilations) < 1:
            raise ValueError(f"refine_dilations must be positive, got {self.refine_dilations}")
        if self.head_blocks < 1:
            raise ValueError(f"head_blocks must be >= 1, got {self.head_blocks}")

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def conv_bn_relu(c_in: int, c_out: int, kernel: int = 3, stride: int = 1) -> nn.Sequential:
    """Dense convolution + BatchNorm + ReLU."""
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, kernel, stride, kernel // 2, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class SeparableBlock(nn.Module):
    """Depthwise 3x3 (stride, dilation) + BN + ReLU, then pointwise 1x1 + BN + ReLU.

    A residual connection is added when the shapes allow it (stride 1, same channels).
    """

    def __init__(self, c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> None:
        super().__init__()
        self.depthwise = nn.Sequential(
            nn.Conv2d(c_in, c_in, 3, stride, dilation, dilation=dilation, groups=c_in, bias=False),
            nn.BatchNorm2d(c_in),
            nn.ReLU(inplace=True),
        )
        self.pointwise = nn.Sequential(
            nn.Conv2d(c_in, c_out, 1, bias=False),
            nn.BatchNorm2d(c_out),
        )
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x: Tensor) -> Tensor:
        y = self.pointwise(self.depthwise(x))
        if self.residual:
            y = y + x
        return F.relu(y)


def _level(c_in: int, c_out: int, depth: int) -> nn.Sequential:
    blocks = [SeparableBlock(c_in, c_out, stride=2)]
    blocks += [SeparableBlock(c_out, c_out) for _ in range(depth - 1)]
    return nn.Sequential(*blocks)


class StageHead(nn.Module):
    """Separable blocks, then a 1x1 convolution to the 9 + 16 output channels."""

    def __init__(self, c_in: int, c_mid: int, dilations: Sequence[int]) -> None:
        super().__init__()
        blocks: list[nn.Module] = []
        c = c_in
        for d in dilations:
            blocks.append(SeparableBlock(c, c_mid, dilation=d))
            c = c_mid
        self.body = nn.Sequential(*blocks)
        self.out = nn.Conv2d(c_mid, NUM_BELIEF + NUM_AFFINITY, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.out(self.body(x))


class DopeLite(nn.Module):
    """The DOPE-Lite network (see the module docstring).

    Args:
        config: hyper-parameters; defaults give the ``dope_lite_base`` model.

    Shapes:
        input ``(B, 3, H, W)`` float, normalised, ``H % 8 == W % 8 == 0``;
        :meth:`forward` returns ``belief (B, 9, H/8, W/8)`` and ``affinity (B, 16, H/8, W/8)``
        of the last stage; :meth:`forward_stages` returns them for every stage (training).
    """

    output_stride = OUTPUT_STRIDE
    num_belief = NUM_BELIEF
    num_affinity = NUM_AFFINITY

    def __init__(self, config: DopeLiteConfig | None = None) -> None:
        super().__init__()
        cfg = config or DopeLiteConfig()
        self.config = cfg
        c4, c8, c16, c32 = cfg.channels
        d4, d8, d16, d32 = cfg.depths
        self.stem = conv_bn_relu(3, cfg.stem_channels, 3, stride=2)
        self.level4 = _level(cfg.stem_channels, c4, d4)
        self.level8 = _level(c4, c8, d8)
        self.level16 = _level(c8, c16, d16)
        self.level32 = _level(c16, c32, d32)
        f = cfg.fpn_channels
        self.lateral32 = conv_bn_relu(c32, f, 1)
        self.lateral16 = conv_bn_relu(c16, f, 1)
        self.lateral8 = conv_bn_relu(c8, f, 1)
        self.smooth16 = SeparableBlock(f, f)
        self.smooth8 = SeparableBlock(f, f)
        n_out = NUM_BELIEF + NUM_AFFINITY
        self.stages = nn.ModuleList(
            [StageHead(f, cfg.head_channels, (1,) * cfg.head_blocks)]
            + [
                StageHead(f + n_out, cfg.head_channels, cfg.refine_dilations)
                for _ in range(cfg.num_stages - 1)
            ]
        )

    @property
    def num_stages(self) -> int:
        return len(self.stages)

    def features(self, x: Tensor) -> Tensor:
        """Stride-8 features ``(B, fpn_channels, H/8, W/8)``."""
        x4 = self.level4(self.stem(x))
        x8 = self.level8(x4)
        x16 = self.level16(x8)
        x32 = self.level32(x16)
        p16 = self.lateral16(x16) + F.interpolate(
            self.lateral32(x32), size=x16.shape[-2:], mode="nearest"
        )
        p16 = self.smooth16(p16)
        p8 = self.lateral8(x8) + F.interpolate(p16, size=x8.shape[-2:], mode="nearest")
        return self.smooth8(p8)

    def forward_stages(self, x: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Every stage's ``(belief (B,9,h,w), affinity (B,16,h,w))``, first stage first."""
        feat = self.features(x)
        outs: list[tuple[Tensor, Tensor]] = []
        y = self.stages[0](feat)
        outs.append((y[:, :NUM_BELIEF], y[:, NUM_BELIEF:]))
        for stage in self.stages[1:]:
            y = stage(torch.cat([feat, y], dim=1))
            outs.append((y[:, :NUM_BELIEF], y[:, NUM_BELIEF:]))
        return outs

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The last stage's ``(belief (B,9,H/8,W/8), affinity (B,16,H/8,W/8))``."""
        return self.forward_stages(x)[-1]


def _build(defaults: DopeLiteConfig, **kwargs) -> DopeLite:
    """Apply keyword overrides (lists become tuples, as YAML gives lists) and build."""
    fields = defaults.to_dict()
    unknown = sorted(set(kwargs) - set(fields))
    if unknown:
        raise ConfigError(
            f"unknown DOPE-Lite hyper-parameter(s) {unknown}; known: {sorted(fields)}"
        )
    merged = {**fields, **kwargs}
    merged = {k: tuple(v) if isinstance(v, list) else v for k, v in merged.items()}
    try:
        return DopeLite(DopeLiteConfig(**merged))
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"invalid DOPE-Lite hyper-parameters {kwargs}: {exc}") from exc


@register_model
def dope_lite_tiny(**kwargs) -> DopeLite:
    """A very small single-stage variant for tests and quick experiments (~0.1 M parameters)."""
    defaults = DopeLiteConfig(
        stem_channels=8, channels=(16, 24, 48, 64), depths=(1, 2, 2, 2),
        fpn_channels=32, head_channels=32, head_blocks=1, num_stages=1,
    )
    return _build(defaults, **kwargs)


@register_model
def dope_lite_small(**kwargs) -> DopeLite:
    """Single-stage variant: the fastest model meant for deployment."""
    defaults = DopeLiteConfig(
        stem_channels=16, channels=(24, 48, 128, 256), depths=(1, 3, 4, 4),
        fpn_channels=64, head_channels=64, head_blocks=2, num_stages=1,
    )
    return _build(defaults, **kwargs)


@register_model
def dope_lite_base(**kwargs) -> DopeLite:
    """Two stages (one refinement), the default model."""
    return _build(DopeLiteConfig(), **kwargs)


@register_model
def dope_lite_large(**kwargs) -> DopeLite:
    """Three stages and a wider trunk: the most accurate variant, still under 5 M parameters."""
    defaults = DopeLiteConfig(
        stem_channels=24, channels=(32, 96, 192, 384), depths=(2, 4, 6, 4),
        fpn_channels=128, head_channels=128, head_blocks=2, num_stages=3,
    )
    return _build(defaults, **kwargs)
