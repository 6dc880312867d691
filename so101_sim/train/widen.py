"""Fine-tune a Diffusion checkpoint into a wider one (``--init-from``): more cameras, or more
spatial-softmax keypoints per camera.

A Diffusion Policy with one encoder shared by its cameras has few places whose shape depends
on how many cameras it reads and how many keypoints each gives:
- the U-Net's conditioning, the linear layer in each residual block (``cond_encoder``) that
  reads ``[diffusion-step embedding, then per observation step: state, each camera's features,
  env state]``;
- with more keypoints, also the encoder's 1x1 keypoint convolution (``pool.nets``: one output
  channel per keypoint) and its last linear layer (``out``: 2 x keypoints in and out).

A checkpoint trained on front and side with 32 keypoints can so start a run on front, side and
wrist, or one with 64 keypoints: its weights are copied to where the same inputs sit in the
wider tensors, and every new column of the conditioning starts at zero (so do the old
features' weights on the new keypoints). The new policy then computes exactly what the
checkpoint did, whatever the new camera shows or the new keypoints read, and training teaches
it to use them from there, instead of from random weights. The new keypoints' own weights keep
the fresh policy's random initialisation: a keypoint that starts at zero would never move.
"""

from __future__ import annotations

from typing import Any

STATE_KEY = "observation.state"
ENV_STATE_KEY = "observation.environment_state"
COND_SUFFIX = ".cond_encoder.1.weight"  # nn.Sequential(Mish, Linear(cond_dim, channels))
KEYPOINT_CONV = "diffusion.rgb_encoder.pool.nets."  # Conv2d(512, keypoints, 1): weight, bias
ENCODER_OUT = "diffusion.rgb_encoder.out."  # Linear(2 x keypoints, 2 x keypoints)


def step_layout(cfg: Any) -> list[tuple[str, int]]:
    """(input, width) in the order one observation step enters the conditioning vector."""
    parts = [(STATE_KEY, int(cfg.robot_state_feature.shape[0]))]
    width = 2 * int(cfg.spatial_softmax_num_keypoints)  # DiffusionRgbEncoder.feature_dim
    parts += [(key, width) for key in cfg.image_features]
    if cfg.env_state_feature is not None:
        parts.append((ENV_STATE_KEY, int(cfg.env_state_feature.shape[0])))
    return parts


def can_widen(then: Any, now: Any) -> bool:
    """Whether a `then` checkpoint fits a `now` policy by widening alone: the same
    architecture, every old camera kept in its order, as many keypoints or more."""
    if then.type != "diffusion" or now.type != "diffusion":
        return False
    old, new = list(then.image_features), list(now.image_features)
    same = ("n_obs_steps", "diffusion_step_embed_dim", "down_dims")
    low_dim = [[p for p in step_layout(c) if p[0] not in c.image_features] for c in (then, now)]
    return not (any(getattr(then, k) != getattr(now, k) for k in same)
                or then.use_separate_rgb_encoder_per_camera  # one encoder per camera: not widened
                or now.use_separate_rgb_encoder_per_camera
                or [k for k in new if k in old] != old
                or low_dim[0] != low_dim[1]  # the same state / env-state inputs
                or now.spatial_softmax_num_keypoints < then.spatial_softmax_num_keypoints)


def added_cameras(then: Any, now: Any) -> list[str]:
    """Image inputs `now` has that `then` lacks, when `then`'s checkpoint can widen into
    `now`; [] when it cannot or need not."""
    if not can_widen(then, now):
        return []
    return [k for k in now.image_features if k not in then.image_features]


def added_keypoints(then: Any, now: Any) -> int:
    """Keypoints per camera `now` has beyond `then`'s, when it can widen; 0 otherwise."""
    if not can_widen(then, now):
        return 0
    return int(now.spatial_softmax_num_keypoints) - int(then.spatial_softmax_num_keypoints)


def widen_conditioning(then: Any, now: Any, tensors: dict[str, Any]) -> list[str]:
    """Rewrite the U-Net's conditioning layers in `tensors` (a state dict of a `then`
    checkpoint) in place to fit a policy built from `now`; returns the added image inputs.
    Each old input's columns go to the start of its slot in the wider vector; the rest is 0."""
    import torch

    if not can_widen(then, now) or step_layout(then) == step_layout(now):
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
    return added_cameras(then, now)


def widen_keypoints(then: Any, now: Any, tensors: dict[str, Any],
                    fresh: dict[str, Any]) -> int:
    """Rewrite the encoder's keypoint layers in `tensors` in place for `now`'s keypoint count,
    taking the new keypoints' weights from `fresh` (the new policy's own initial state dict);
    returns the keypoints added per camera (0 = nothing done). The old features read the new
    keypoints through zero weights, so they stay what they were; the new features are random
    and enter the U-Net through the zero columns `widen_conditioning` leaves."""
    added = added_keypoints(then, now)
    if not added:
        return 0
    k = 2 * int(then.spatial_softmax_num_keypoints)  # flattened (x, y) per keypoint: old first
    for name, rows in ((KEYPOINT_CONV + "weight", k // 2), (ENCODER_OUT + "weight", k)):
        got = tuple(tensors[name].shape) if name in tensors else None
        if got is None or got[0] != rows:  # the config and the weights disagree: not widened
            raise ValueError(f"{name} is {got}, not the {rows} rows its config.json's "
                             f"{k // 2} keypoints need; the checkpoint is inconsistent: "
                             "start from one that `so101-sim eval` loads")
    for name in ("weight", "bias"):
        conv = fresh[KEYPOINT_CONV + name].clone()
        conv[:k // 2] = tensors[KEYPOINT_CONV + name]
        tensors[KEYPOINT_CONV + name] = conv
    out_w, out_b = fresh[ENCODER_OUT + "weight"].clone(), fresh[ENCODER_OUT + "bias"].clone()
    out_w[:k, :k] = tensors[ENCODER_OUT + "weight"]
    out_w[:k, k:] = 0
    out_b[:k] = tensors[ENCODER_OUT + "bias"]
    tensors[ENCODER_OUT + "weight"], tensors[ENCODER_OUT + "bias"] = out_w, out_b
    return added
