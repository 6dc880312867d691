"""Max pooling in channels-last layout for inference on CPU: the same values, less time.

torch's CPU max pooling on a contiguous NCHW tensor is a scalar loop: on the ResNet-18 stem of a
pick_place_diffusion forward (32 images of 64 x 30 x 40) it took 18 ms on one thread here,
about 8% of the whole DDIM-10 forward, while the channels-last kernel with both layout copies
took 3.5 ms (benchmarks/README.md, bench_forward_rows.py). A maximum is exact, so the pooled
values are bit for bit those of the default kernel; the output goes back to NCHW so every
layer after it sees the tensor it saw before. Only the indices of tied maxima could differ, so
the default kernel still runs whenever gradients are on or indices are asked for.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["ChannelsLastMaxPool2d", "use_channels_last_pooling", "use_default_pooling"]


class ChannelsLastMaxPool2d(nn.MaxPool2d):
    """``nn.MaxPool2d`` that pools 4-D CPU inputs in channels-last layout under no_grad."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (self.return_indices or torch.is_grad_enabled() or x.dim() != 4
                or x.device.type != "cpu"):
            return super().forward(x)
        pooled = super().forward(x.contiguous(memory_format=torch.channels_last))
        return pooled.contiguous()


def _swap(module: nn.Module, old: type, new: type) -> int:
    swapped = 0
    for parent in module.modules():
        for name, child in list(parent.named_children()):
            if type(child) is old:
                setattr(parent, name, new(child.kernel_size, child.stride, child.padding,
                                          child.dilation, child.return_indices,
                                          child.ceil_mode))
                swapped += 1
    return swapped


def use_channels_last_pooling(module: nn.Module) -> int:
    """Swap every plain ``nn.MaxPool2d`` inside ``module`` for the channels-last one.

    Returns how many were swapped. Parameters are untouched (pooling has none), so a
    checkpoint's weights and fingerprint stay what they were.
    """
    return _swap(module, nn.MaxPool2d, ChannelsLastMaxPool2d)


def use_default_pooling(module: nn.Module) -> int:
    """Undo ``use_channels_last_pooling`` (for A/B timings and tests); returns the count."""
    return _swap(module, ChannelsLastMaxPool2d, nn.MaxPool2d)
