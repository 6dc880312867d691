"""A tiny, untrained lerobot DiffusionPolicy checkpoint for tests and benchmark development.

The weights are random (seeded), so the policy fails the task, but it loads, normalises and
samples exactly like a trained checkpoint: lerobot's config.json, model.safetensors and the saved
pre/post-processors, plus the trainer's `so101_sim_train.json` sidecar.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

REST = [-10.374, -81.670, 77.846, 2.681, 123.209, 6.495]


def make_tiny_diffusion_checkpoint(out_dir: str | Path, input_size: tuple[int, int] = (48, 64),
                                   dataset_image_size: tuple[int, int] | None = (96, 128),
                                   cameras: tuple[str, ...] = ("front", "side"),
                                   state_dim: int = 6, seed: int = 0,
                                   noise_scheduler_type: str = "DDIM",
                                   num_inference_steps: int | None = 10,
                                   keypoints: int = 8) -> Path:
    """Write a DiffusionPolicy checkpoint (To=2, Tp=16, Ta=8) into `out_dir` and return it."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    h, w = input_size
    inputs = {"observation.state": PolicyFeature(type=FeatureType.STATE, shape=(state_dim,))}
    for cam in cameras:
        inputs[f"observation.images.{cam}"] = PolicyFeature(type=FeatureType.VISUAL,
                                                           shape=(3, h, w))
    config = DiffusionConfig(
        input_features=inputs,
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(6,))},
        n_obs_steps=2, horizon=16, n_action_steps=8,
        vision_backbone="resnet18", pretrained_backbone_weights=None, use_group_norm=True,
        crop_shape=(h - 16, w - 24), crop_is_random=True,
        use_separate_rgb_encoder_per_camera=False, spatial_softmax_num_keypoints=keypoints,
        down_dims=(16, 32), kernel_size=3, n_groups=4, diffusion_step_embed_dim=16,
        noise_scheduler_type=noise_scheduler_type, num_inference_steps=num_inference_steps,
        device="cpu",
    )
    torch.manual_seed(seed)
    policy = DiffusionPolicy(config)
    policy.save_pretrained(out)
    lo = torch.tensor(REST) - torch.tensor([60.0, 60.0, 60.0, 60.0, 60.0, 10.0])
    hi = torch.tensor(REST) + torch.tensor([60.0, 60.0, 60.0, 60.0, 60.0, 60.0])
    stats = {
        "observation.state": {"min": lo[:state_dim], "max": hi[:state_dim]},
        "action": {"min": lo, "max": hi},
    }
    for cam in cameras:
        stats[f"observation.images.{cam}"] = {"mean": torch.full((3, 1, 1), 0.5),
                                              "std": torch.full((3, 1, 1), 0.25)}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    if dataset_image_size is not None:
        (out / "so101_sim_train.json").write_text(
            json.dumps({"dataset_image_size": list(dataset_image_size)}))
    return out


def short_task(out_dir: str | Path, max_steps: int = 40) -> Path:
    """The default task with episodes cut to `max_steps` (fast closed-loop tests)."""
    import re

    from so101_sim.utils.paths import envs_dir

    text = (envs_dir() / "pick_place.toml").read_text()
    text, n = re.subn(r"(?m)^max_steps\s*=\s*\d+", f"max_steps = {max_steps}", text)
    assert n == 1, "pick_place.toml has no max_steps line"
    path = Path(out_dir) / f"pick_place_{max_steps}.toml"
    path.write_text(text)
    return path
