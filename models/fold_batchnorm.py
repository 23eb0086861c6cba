"""Batch-norm folding for inference: a copy of a network whose convolutions absorb their BN.

In eval mode a ``BatchNorm2d`` after a convolution is a per-channel affine map, so it can be
folded into the convolution's weights and bias (``torch.nn.utils.fusion.fuse_conv_bn_eval``)
and the BN layer dropped. The outputs are the same up to float round-off; eager inference
skips one pass over every feature map: DOPE-Lite small on two CPU threads, 640x480, ~35 %
less time (``benchmarks/bench_pose_speed.py``). onnxruntime does the same fold itself when
it loads an exported graph.
"""

from __future__ import annotations

import copy

from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

__all__ = ["fold_batchnorm"]


def fold_batchnorm(net: nn.Module) -> tuple[nn.Module, int]:
    """An eval-mode copy of ``net`` with every ``Conv2d`` directly followed by a
    ``BatchNorm2d`` inside an ``nn.Sequential`` folded into one convolution.

    The BN's running statistics and affine parameters are used (eval-mode behaviour); a BN
    without running statistics, or not right after a convolution of matching channels, is
    left as it is. ``net`` itself is not changed. Attributes set on ``net`` (for instance a
    DOPE-Lite network's ``weights_record``) are copied with it.

    Args:
        net: any module.

    Returns:
        The folded copy (in eval mode) and the number of BN layers folded.
    """
    folded = copy.deepcopy(net).eval()
    count = 0
    for module in folded.modules():
        if not isinstance(module, nn.Sequential):
            continue
        names = list(module._modules)
        for first, second in zip(names, names[1:], strict=False):
            conv, bn = module._modules[first], module._modules[second]
            if (isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d)
                    and bn.track_running_stats and bn.running_mean is not None
                    and bn.num_features == conv.out_channels):
                module._modules[first] = fuse_conv_bn_eval(conv, bn)
                module._modules[second] = nn.Identity()
                count += 1
    return folded, count
