"""A tiny, untrained lerobot ACT checkpoint (chunked, or with temporal ensembling) for tests."""

from __future__ import annotations

from pathlib import Path

import torch

REST = [-10.374, -81.670, 77.846, 2.681, 123.209, 6.495]


def make_tiny_act_checkpoint(out_dir: str | Path, input_size: tuple[int, int] = (48, 64),
                             temporal_ensemble_coeff: float | None = None,
                             chunk_size: int = 8, seed: int = 0) -> Path:
    """ACT with random weights; n_action_steps = chunk_size, or 1 with temporal ensembling."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    h, w = input_size
    inputs = {"observation.state": PolicyFeature(type=FeatureType.STATE, shape=(6,))}
    for cam in ("front", "side"):
        inputs[f"observation.images.{cam}"] = PolicyFeature(type=FeatureType.VISUAL,
                                                           shape=(3, h, w))
    config = ACTConfig(
        input_features=inputs,
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(6,))},
        chunk_size=chunk_size,
        n_action_steps=1 if temporal_ensemble_coeff is not None else chunk_size,
        temporal_ensemble_coeff=temporal_ensemble_coeff,
        vision_backbone="resnet18", pretrained_backbone_weights=None, dim_model=32, n_heads=2,
        dim_feedforward=64, n_encoder_layers=1, n_decoder_layers=1, use_vae=False,
        device="cpu",
    )
    torch.manual_seed(seed)
    ACTPolicy(config).save_pretrained(out)
    rest = torch.tensor(REST)
    stats = {"observation.state": {"mean": rest, "std": torch.full((6,), 20.0)},
             "action": {"mean": rest, "std": torch.full((6,), 20.0)}}
    for cam in ("front", "side"):
        stats[f"observation.images.{cam}"] = {"mean": torch.full((3, 1, 1), 0.5),
                                              "std": torch.full((3, 1, 1), 0.25)}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return out
