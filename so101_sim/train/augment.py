"""Image augmentation for training: lerobot's `ImageTransforms`, configured by a preset's
``[augment]`` section.

Why: a policy trained on the nominal scene loses most of its points on pick_place_dr to
appearance draws (table and robot colours, camera shifts; see benchmarks/baselines/README.md),
and colour jitter plus small affine shifts of the training frames are the usual remedy.

The section's keys are those of lerobot's `ImageTransformsConfig` less ``enable`` (a preset with
the section is enabled): ``max_num_transforms``, ``random_order`` and ``tfs``, a table of
``{weight, type, kwargs}`` per transform. Without ``tfs`` lerobot's default set is used
(brightness, contrast, saturation, hue, sharpness, affine). As in lerobot, each training sample
gets its own draw, shared by all of its observation frames, and drawn per camera; the draws come
from torch's global RNG, which checkpoints save, so a resumed run is the same run.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from so101_sim.utils.text import did_you_mean

if TYPE_CHECKING:  # annotations only: lerobot's transforms load when a preset uses them
    from lerobot.transforms import ImageTransformsConfig

#: The ``[augment]`` keys a preset may set.
AUGMENT_KEYS = ("max_num_transforms", "random_order", "tfs")
_TF_KEYS = ("weight", "type", "kwargs")


def transforms_config(section: dict[str, Any], where: str = "[augment]"
                      ) -> ImageTransformsConfig:
    """lerobot's `ImageTransformsConfig` (enabled) from a preset's ``[augment]`` table.

    Raises ValueError naming the bad key or transform; the transforms are built once here so a
    typo in a type name fails when the preset loads, not hours into a run.
    """
    from lerobot.transforms import ImageTransformConfig, ImageTransforms, ImageTransformsConfig

    unknown = sorted(set(section) - set(AUGMENT_KEYS))
    if unknown:
        hint = did_you_mean(unknown[0], AUGMENT_KEYS) if len(unknown) == 1 else ""
        raise ValueError(f"{where}: unknown keys {unknown}{hint}; expected some of "
                         f"{list(AUGMENT_KEYS)}")
    kwargs: dict[str, Any] = {"enable": True}
    if "max_num_transforms" in section:
        kwargs["max_num_transforms"] = int(section["max_num_transforms"])
    if "random_order" in section:
        kwargs["random_order"] = bool(section["random_order"])
    if "tfs" in section:
        tfs = {}
        for name, tf in section["tfs"].items():
            if not isinstance(tf, dict) or set(tf) - set(_TF_KEYS) or "type" not in tf:
                raise ValueError(f"{where}: transform {name!r} = {tf!r}; expected a table with "
                                 f"`type` and optionally `weight` and `kwargs`")
            kw = {k: tuple(v) if isinstance(v, list) else v
                  for k, v in tf.get("kwargs", {}).items()}
            tfs[name] = ImageTransformConfig(weight=float(tf.get("weight", 1.0)),
                                             type=str(tf["type"]), kwargs=kw)
        if not tfs:
            raise ValueError(f"{where}: `tfs` is empty; leave it out for lerobot's default set")
        kwargs["tfs"] = tfs
    cfg = ImageTransformsConfig(**kwargs)
    if cfg.max_num_transforms < 1:
        raise ValueError(f"{where}: max_num_transforms {cfg.max_num_transforms} must be >= 1")
    try:
        ImageTransforms(cfg)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: {e}") from None
    return cfg


class FrameAugmenter:
    """Applies the preset's transforms to the camera frames of a training batch, in place."""

    def __init__(self, section: dict[str, Any]) -> None:
        from lerobot.transforms import ImageTransforms

        self.transforms = ImageTransforms(transforms_config(section))

    def __call__(self, batch: dict[str, Any]) -> dict[str, Any]:
        for key, frames in batch.items():
            if not key.startswith("observation.images."):
                continue
            # frames: [B, (T,) 3, h, w] in [0, 1]; one draw per sample covers its T frames.
            batch[key] = torch.stack([self.transforms(f) for f in frames]).clamp_(0.0, 1.0)
        return batch
