"""Fine-tune a Diffusion checkpoint with more cameras than it was trained on (``--init-from``).

A Diffusion Policy with one encoder shared by its cameras has only one place whose shape
depends on the number of cameras: the U-Net's conditioning, the linear layer in each residual
block (``cond_encoder``) that reads ``[diffusion-step embedding, then per observation step:
state, each camera's features, env state]``. A checkpoint trained on front and side can so
start a run on front, side and wrist: its columns are copied to where the same inputs sit in
the wider vector and the new camera's columns start at zero. The new policy then computes
exactly what the checkpoint did, whatever the new camera shows, and training teaches it to use
the new view from there, instead of from random weights.
"""

from __future__ import annotations

from typing import Any

STATE_KEY = "observation.state"
ENV_STATE_KEY = "observation.environment_state"
COND_SUFFIX = ".cond_encoder.1.weight"  # nn.Sequential(Mish, Linear(cond_dim, channels))


def step_layout(cfg: Any) -> list[tuple[str, int]]:
    """(input, width) in the order one observation step enters the conditioning vector."""
    parts = [(STATE_KEY, int(cfg.robot_state_feature.shape[0]))]
    width = 2 * int(cfg.spatial_softmax_num_keypoints)  # DiffusionRgbEncoder.feature_dim
    parts += [(key, width) for key in cfg.image_features]
    if cfg.env_state_feature is not None:
        parts.append((ENV_STATE_KEY, int(cfg.env_state_feature.shape[0])))
    return parts


def added_cameras(then: Any, now: Any) -> list[str]:
    """Image inputs `now` has that `then` lacks, when `then`'s checkpoint can widen into
    `now` (same architecture otherwise); [] when it cannot or need not."""
    if then.type != "diffusion" or now.type != "diffusion":
        return []
    old, new = list(then.image_features), list(now.image_features)
    same = ("n_obs_steps", "spatial_softmax_num_keypoints", "diffusion_step_embed_dim",
            "down_dims")
    low_dim = [[p for p in step_layout(c) if p[0] not in c.image_features] for c in (then, now)]
    if (any(getattr(then, k) != getattr(now, k) for k in same)
            or then.use_separate_rgb_encoder_per_camera  # one encoder per camera: not widened
            or now.use_separate_rgb_encoder_per_camera
            or [k for k in new if k in old] != old  # every old camera kept, in its order
            or low_dim[0] != low_dim[1]):  # the same state / env-state inputs
        return []
    return [k for k in new if k not in old]


def widen_conditioning(then: Any, now: Any, tensors: dict[str, Any]) -> list[str]:
    """Rewrite `tensors` (a state dict of a `then` checkpoint) in place to fit a policy built
    from `now`, which adds cameras; returns the added image inputs ([] = nothing done)."""
    import torch

    added = added_cameras(then, now)
    if not added:
        return []
    embed, steps = int(now.diffusion_step_embed_dim), int(now.n_obs_steps)
    old_parts, new_parts = step_layout(then), step_layout(now)
    old_w, new_w = sum(w for _, w in old_parts), sum(w for _, w in new_parts)
    new_at, at = {}, 0
    for key, w in new_parts:
        new_at[key], at = at, at + w
    for name, weight in list(tensors.items()):
        if not name.endswith(COND_SUFFIX) or weight.shape[1] != embed + steps * old_w:
            continue
        wide = torch.zeros(weight.shape[0], embed + steps * new_w, dtype=weight.dtype)
        wide[:, :embed] = weight[:, :embed]
        for t in range(steps):
            src = embed + t * old_w
            for key, w in old_parts:
                dst = embed + t * new_w + new_at[key]
                wide[:, dst:dst + w] = weight[:, src:src + w]
                src += w
        tensors[name] = wide
    return added
