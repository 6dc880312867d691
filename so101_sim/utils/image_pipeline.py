"""The one resize that camera frames go through before they reach a policy.

Training (frames decoded from the dataset's videos) and evaluation (frames rendered by the env)
both call `resize_frames`, so a policy sees images made the same way in both. Imports torch:
only the trainer and the harness import this module.
"""

from __future__ import annotations

import numpy as np
import torch
from torchvision.transforms.v2 import functional as F


def resize_frames(frames: np.ndarray | torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Resize uint8 frames to `size` (height, width) with antialiased bilinear filtering.

    `frames` is [..., H, W, 3] (channels last, as rendered) or [..., 3, H, W] (channels first, as
    decoded); the result is a uint8 tensor [..., 3, h, w]. Frames already at `size` are returned
    unchanged, which keeps the render-at-policy-resolution path free of any resampling.
    """
    t = torch.as_tensor(frames)
    if t.dtype != torch.uint8:
        raise TypeError(f"resize_frames expects uint8 frames, got {t.dtype}; pass the raw "
                        "rendered or decoded frames, before any normalisation")
    if t.ndim < 3:
        raise ValueError(f"resize_frames expects [..., H, W, 3] or [..., 3, H, W], got shape "
                         f"{tuple(t.shape)}")
    if t.shape[-1] == 3 and t.shape[-3] != 3:
        t = t.movedim(-1, -3)
    elif t.shape[-3] != 3:
        raise ValueError(f"resize_frames expects 3 colour channels, got shape {tuple(t.shape)}")
    h, w = int(size[0]), int(size[1])
    if tuple(t.shape[-2:]) == (h, w):
        return t.contiguous()
    lead = t.shape[:-3]
    flat = t.reshape(-1, *t.shape[-3:])
    out = F.resize(flat, [h, w], interpolation=F.InterpolationMode.BILINEAR, antialias=True)
    return out.reshape(*lead, 3, h, w)


def resize_pixels(pixels: dict[str, np.ndarray], size: tuple[int, int]) -> dict[str, np.ndarray]:
    """``{camera: HxWx3 uint8}`` -> the same cameras resized to `size` with ``resize_frames``
    (one call for all cameras), channels last, as numpy."""
    cams = list(pixels)
    small = resize_frames(np.stack([pixels[c] for c in cams]), size)
    hwc = small.permute(0, 2, 3, 1).contiguous().numpy()
    return {c: hwc[k] for k, c in enumerate(cams)}
