"""Parameter and FLOP counts of a network (FLOPs from ``torch.utils.flop_counter``)."""

from __future__ import annotations

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

__all__ = ["count_parameters", "count_flops"]


def count_parameters(net: nn.Module) -> int:
    """Number of parameters (buffers such as BatchNorm statistics excluded)."""
    return sum(p.numel() for p in net.parameters())


def count_flops(net: nn.Module, height: int, width: int, batch: int = 1) -> int:
    """FLOPs of one forward pass on a ``(batch, 3, height, width)`` input.

    Counted by :class:`torch.utils.flop_counter.FlopCounterMode`, which counts a
    multiply-accumulate as 2 FLOPs and covers convolutions and matrix products (element-wise
    operations such as BatchNorm, ReLU and additions are not counted).
    """
    was_training = net.training
    net.eval()
    try:
        param = next(net.parameters(), None)
        device = param.device if param is not None else torch.device("cpu")
        x = torch.zeros(batch, 3, height, width, device=device)
        with torch.no_grad(), FlopCounterMode(display=False) as counter:
            net(x)
        return int(counter.get_total_flops())
    finally:
        net.train(was_training)
