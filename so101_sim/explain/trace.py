"""Run one batch through a DiffusionPolicy's real modules and record every number on the page.

`trace` is the measuring half of `so101-sim explain` (see `explain`): one `policy.forward`
with the given noise and step k (`explain.hooks.fixed_draws`), one `predict_action_chunk` with
given initial noise, forward hooks on the encoder stages, spatial softmax, step encoder, U-Net.
What it derives itself (pixel coordinates, squared errors, RMSE) is display arithmetic on those
recorded tensors; where a layout matters (which image is which, where the state sits in the
conditioning vector, where the crop was taken) it is found by comparing tensors, not assumed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from so101_sim.explain.errors import ExplainError
from so101_sim.explain.hooks import (
    Hooks,
    crop_offset,
    find_slice,
    fixed_draws,
    tolist,
)
from so101_sim.utils.image_pipeline import resize_frames

STATE_KEY = "observation.state"
N_PIXEL_CHANNELS = 4  # feature channels shown at the traced pixel


def step_label(offset: int) -> str:
    """Frame offset relative to the current frame t: -1 -> 't-1', 0 -> 't'."""
    return "t" if offset == 0 else f"t{offset:+d}"


def _build_batch(cfg: Any, item: dict[str, Any]) -> tuple[dict, dict[str, np.ndarray]]:
    """Un-normalised policy batch (frames through `resize_frames`, as training) + display
    images (original and policy-size frames, uint8 HWC)."""
    batch: dict[str, Any] = {}
    images: dict[str, np.ndarray] = {}
    for key in cfg.input_features:
        if key in cfg.image_features:
            raw = (item[key] * 255).round().clamp(0, 255).to(torch.uint8)  # decoded uint8 frames
            small = resize_frames(raw, tuple(cfg.image_features[key].shape[1:]))
            batch[key] = small.float().div(255.0)[None]
            cam = key.split(".")[-1]
            for s in range(raw.shape[0]):
                images[f"{cam}/orig/{s}"] = raw[s].permute(1, 2, 0).numpy()
                images[f"{cam}/policy/{s}"] = small[s].permute(1, 2, 0).numpy()
        else:
            batch[key] = item[key][None]
    batch["action"] = item["action"][None]
    batch["action_is_pad"] = item["action_is_pad"][None]
    return batch, images


def _encoder_hooks(hooks: Hooks, encoder: Any, rec: dict[str, list]) -> None:
    """Per call of a DiffusionRgbEncoder: its input, the backbone's input (cropped), every
    backbone stage's output, the keypoint heatmaps, the keypoints and the feature vector."""
    def keep(name: str, use_input: bool = False) -> Callable[..., None]:
        def hook(_m: Any, args: tuple, out: Any = None) -> None:
            rec.setdefault(name, []).append((args[0] if use_input else out).detach().clone())
        return hook

    hooks.add(encoder.register_forward_pre_hook(keep("input", True)))
    if encoder.resize is not None:
        hooks.add(encoder.resize.register_forward_hook(keep("resized")))
    hooks.add(encoder.backbone.register_forward_pre_hook(keep("crop", True)))
    for i, stage in enumerate(encoder.backbone):
        hooks.add(stage.register_forward_hook(keep(f"stage{i}")))
    if encoder.pool.nets is not None:
        hooks.add(encoder.pool.nets.register_forward_hook(keep("heatmap")))
    hooks.add(encoder.pool.register_forward_hook(keep("keypoints")))
    hooks.add(encoder.register_forward_hook(keep("feature")))


def _stage_names(cfg: Any, backbone: Any) -> list[str]:
    """torchvision's names for the backbone's stages (conv1, bn1, ..., layer4)."""
    import torchvision

    names = [n for n, _ in getattr(torchvision.models, cfg.vision_backbone)(
        weights=None).named_children()]
    return names[:len(backbone)] if len(names) >= len(backbone) else [
        str(i) for i in range(len(backbone))]


def _describe(m: torch.nn.Module) -> str:
    """A short description of a backbone stage, read from the module."""
    if isinstance(m, torch.nn.Conv2d):
        return (f"Conv2d({m.in_channels}→{m.out_channels}, {m.kernel_size[0]}×{m.kernel_size[1]}"
                f", stride {m.stride[0]}, pad {m.padding[0]})")
    if isinstance(m, torch.nn.GroupNorm):
        return f"GroupNorm({m.num_groups} groups, {m.num_channels} channels)"
    if isinstance(m, torch.nn.MaxPool2d):
        return f"MaxPool2d({m.kernel_size}, stride {m.stride}, pad {m.padding})"
    if isinstance(m, torch.nn.Sequential) and len(m):
        convs = [c for c in m.modules() if isinstance(c, torch.nn.Conv2d)]
        return (f"{len(m)} × {type(m[0]).__name__}({convs[0].in_channels}→"
                f"{convs[0].out_channels}, stride {convs[0].stride[0]}), {len(convs)} convs")
    return type(m).__name__


def _map(v: float, n_from: int, n_to: int) -> float:
    """Pixel-centre coordinate mapping between two resolutions of the same image."""
    return (v + 0.5) * n_to / n_from - 0.5


def _cell_to_px(v: torch.Tensor, cells: int, pixels: int) -> torch.Tensor:
    """SpatialSoftmax coordinate -> crop pixel. Its grid puts -1 and +1 on the first and last
    feature cell; the cells tile the crop evenly, so a coordinate lands on a cell centre."""
    return ((v + 1) / 2 * (cells - 1) + 0.5) * pixels / cells - 0.5


def _normaliser_stats(pre: Any, key: str) -> dict[str, list] | None:
    for step in getattr(pre, "steps", []):
        stats = getattr(step, "stats", None)
        if hasattr(step, "norm_map") and stats and key in stats:
            return {k: np.asarray(tolist(torch.as_tensor(v))).reshape(-1).tolist()
                    for k, v in stats[key].items()}
    return None


def _encoder_numbers(cfg: Any, model: Any, pre: Any, batch: dict, rec: dict,
                     images: dict[str, np.ndarray]) -> dict[str, Any]:
    cams = list(cfg.image_features)
    enc = model.rgb_encoder if not isinstance(model.rgb_encoder, torch.nn.ModuleList) \
        else model.rgb_encoder[0]
    cat = {name: torch.cat(v) for name, v in rec.items()}
    n_obs = batch[STATE_KEY].shape[1]
    # which (obs step, camera) each encoded image is, read by comparing with the batch
    which: list[tuple[int, str]] = []
    for img in cat["input"]:
        hit = [(s, key) for key in cams for s in range(n_obs) if torch.equal(batch[key][0, s], img)]
        if not hit:
            raise ExplainError("an image the encoder saw matches no batch image")
        # identical frames (padding copies at an episode start) match several: take a free one
        which.append(next((h for h in hit if h not in which), hit[0]))
    source = cat.get("resized", cat["input"])
    out: dict[str, Any] = {"feature_dim": int(cat["feature"].shape[1]),
                           "feature_grid": list(cat[f"stage{len(enc.backbone) - 1}"].shape[2:]),
                           "n_keypoints": int(cat["keypoints"].shape[1]),
                           "crop_shape": list(cat["crop"].shape[2:]),
                           "order": [f"{step_label(cfg.observation_delta_indices[s])} "
                                     f"{key.split('.')[-1]}" for s, key in which]}
    # stages, traced at the centre pixel of the current frame of the first camera
    i_star = which.index((n_obs - 1, cams[0]))
    ch, cw = out["crop_shape"]
    cy, cx = ch // 2, cw // 2
    stages = [{"name": "input (cropped, normalised)", "desc": "what the backbone sees",
               "shape": list(cat["crop"].shape[1:]),
               "values": tolist(cat["crop"][i_star, :, cy, cx])}]
    for i, (name, stage) in enumerate(zip(_stage_names(cfg, enc.backbone), enc.backbone,
                                          strict=True)):
        t = cat[f"stage{i}"][i_star]
        fy, fx = cy * t.shape[1] // ch, cx * t.shape[2] // cw
        stages.append({"name": name, "desc": _describe(stage), "shape": list(t.shape),
                       "cell": [fy, fx], "channels": int(t.shape[0]),
                       "values": tolist(t[:N_PIXEL_CHANNELS, fy, fx])})
    if "heatmap" in cat:
        stages.append({"name": "pool.nets", "desc": f"Conv2d 1×1 → "
                       f"{cat['heatmap'].shape[1]} keypoint heatmaps",
                       "shape": list(cat["heatmap"].shape[1:])})
        attn = torch.softmax(cat["heatmap"].flatten(2), -1)
        out["attention_peak"] = float(attn.max(-1).values.mean())
        out["attention_uniform"] = 1.0 / attn.shape[-1]
    stages.append({"name": "SpatialSoftmax", "desc": "softmax per heatmap → expected (x, y)",
                   "shape": list(cat["keypoints"].shape[1:])})
    stages.append({"name": "out + ReLU", "desc": f"Linear({enc.out.in_features}→"
                   f"{enc.out.out_features}) + ReLU on the flattened keypoints",
                   "shape": list(cat["feature"].shape[1:])})
    out["stages"] = stages
    # the traced pixel through resize and normalisation
    key0 = cams[0]
    s_star, src = n_obs - 1, source[i_star]
    offset = crop_offset(src, cat["crop"][i_star])
    top, left = offset if offset else (0, 0)
    ph, pw = batch[key0].shape[-2:]
    sy, sx = cy + top, cx + left
    py, px = round(_map(sy, src.shape[1], ph)), round(_map(sx, src.shape[2], pw))
    orig = images[f"{key0.split('.')[-1]}/orig/{s_star}"]
    policy_img = images[f"{key0.split('.')[-1]}/policy/{s_star}"]
    oy = round(_map(py, ph, orig.shape[0]))
    ox = round(_map(px, pw, orig.shape[1]))
    out["pixel"] = {"camera": key0, "step": step_label(cfg.observation_delta_indices[s_star]),
                    "orig_xy": [ox, oy], "orig_rgb": orig[oy, ox].tolist(),
                    "policy_xy": [px, py], "policy_rgb": policy_img[py, px].tolist(),
                    "scaled": [v / 255.0 for v in policy_img[py, px].tolist()],
                    "normalised": tolist(batch[key0][0, s_star, :, py, px]),
                    "crop_xy": [cx, cy], "normaliser": _normaliser_stats(pre, key0)}
    # keypoints in crop, policy-image and original pixels, per (camera, obs step)
    kps: dict[str, Any] = {}
    gh, gw = out["feature_grid"]
    for i, (s, key) in enumerate(which):
        off = crop_offset(source[i], cat["crop"][i])
        t, lft = off if off else (0, 0)
        xy = cat["keypoints"][i]
        crop_px = torch.stack([_cell_to_px(xy[:, 0], gw, cw), _cell_to_px(xy[:, 1], gh, ch)], 1)
        src_h, src_w = source[i].shape[1:]
        pol = [[_map(x + lft, src_w, pw), _map(y + t, src_h, ph)] for x, y in crop_px.tolist()]
        ih, iw = images[f"{key.split('.')[-1]}/orig/{s}"].shape[:2]
        kps[f"{key.split('.')[-1]}/{s}"] = {
            "normalised": tolist(xy), "crop_px": tolist(crop_px), "policy_px": pol,
            "orig_px": [[_map(x, pw, iw), _map(y, ph, ih)] for x, y in pol],
            "crop_offset": list(off) if off else None,
            "crop_box_policy": [lft * pw / src_w - 0.5, t * ph / src_h - 0.5,
                                cw * pw / src_w, ch * ph / src_h] if off else None}
    out["keypoints"] = kps
    out["features"] = {label: tolist(cat["feature"][i]) for i, label in enumerate(out["order"])}
    return out


def _cond_layout(cfg: Any, gc: torch.Tensor, batch: dict, enc: dict) -> list[dict[str, Any]]:
    """Where each state vector and image feature sits in the global conditioning vector."""
    taken: set[int] = set()
    layout = []
    n_obs = batch[STATE_KEY].shape[1]
    pieces = [(f"state {step_label(cfg.observation_delta_indices[s])}", batch[STATE_KEY][0, s])
              for s in range(n_obs)]
    pieces += [(f"image {label}", torch.tensor(v)) for label, v in enc["features"].items()]
    if "observation.environment_state" in batch:
        pieces += [(f"env state {step_label(cfg.observation_delta_indices[s])}",
                    batch["observation.environment_state"][0, s]) for s in range(n_obs)]
    for name, piece in pieces:
        start = find_slice(gc, piece.float(), taken)
        if start is not None:
            taken.update(range(start, start + piece.numel()))
        layout.append({"name": name, "start": start, "end": None if start is None
                       else start + piece.numel()})
    return sorted(layout, key=lambda r: (r["start"] is None, r["start"] or 0))


def _unet_hooks(hooks: Hooks, unet: Any) -> None:
    """Every block of the U-Net, the timestep encoder's layers, the first FiLM input."""
    for part in ("down_modules", "up_modules"):
        for i, level in enumerate(getattr(unet, part)):
            for j, m in enumerate(level):
                if not isinstance(m, torch.nn.Identity):
                    hooks.every_call(f"{part}.{i}.{j}", m)
    for i, m in enumerate(unet.mid_modules):
        hooks.every_call(f"mid_modules.{i}", m)
    hooks.every_call("final_conv", unet.final_conv)
    for i, m in enumerate(unet.diffusion_step_encoder):
        hooks.output(f"step_encoder.{i}", m)
    film = next(m for n, m in unet.named_modules() if n.endswith("cond_encoder"))
    hooks.input("film_in", film)
    hooks.output("film_out", film)


def trace(policy: Any, pre: Any, post: Any, item: dict[str, Any], k: int,
          seed: int) -> tuple[dict[str, Any], dict[str, np.ndarray], dict, torch.Tensor]:
    """Numbers and images for the page, the preprocessed batch, and the loss noise."""
    cfg, model = policy.config, policy.diffusion
    raw, images = _build_batch(cfg, item)
    batch = pre(dict(raw))
    gen = torch.Generator().manual_seed(seed)
    eps = torch.randn(tuple(batch["action"].shape), generator=gen)
    rec: dict[str, list] = {}
    with Hooks() as hooks, torch.no_grad():
        for enc in (model.rgb_encoder if isinstance(model.rgb_encoder, torch.nn.ModuleList)
                    else [model.rgb_encoder]):
            _encoder_hooks(hooks, enc, rec)
        hooks.every_call("unet", model.unet)
        _unet_hooks(hooks, model.unet)
        with fixed_draws(eps, k):
            loss, _ = policy.forward(batch)
    (noisy, timesteps), kw = next(c[1] for c in hooks.calls if c[0] == "unet")
    pred = next(c[2] for c in hooks.calls if c[0] == "unet")
    gc = kw["global_cond"]
    numbers: dict[str, Any] = {"encoder": _encoder_numbers(cfg, model, pre, batch, rec, images)}
    enc = numbers["encoder"]
    enc["global_cond"] = {"shape": list(gc.shape[1:]), "values": tolist(gc[0]),
                          "layout": _cond_layout(cfg, gc[0], batch, enc)}
    cams = list(cfg.image_features)
    n_obs = raw[STATE_KEY].shape[1]
    numbers["frames"] = {
        "steps": [step_label(d) for d in cfg.observation_delta_indices],
        "is_pad": {key.split(".")[-1]: tolist(item.get(f"{key}_is_pad",
                                                         torch.zeros(n_obs, dtype=torch.bool)))
                   for key in cams},
        "policy_image_size": list(cfg.image_features[cams[0]].shape[1:]),
    }
    numbers["state"] = {"raw": tolist(raw[STATE_KEY][0]), "normalised": tolist(batch[STATE_KEY][0]),
                        "is_pad": tolist(item.get(f"{STATE_KEY}_is_pad",
                                                   torch.zeros(n_obs, dtype=torch.bool)))}
    a0 = batch["action"][0]
    numbers["actions"] = {"raw": tolist(raw["action"][0]), "normalised": tolist(a0),
                          "offsets": list(cfg.action_delta_indices),
                          "is_pad": tolist(raw["action_is_pad"][0]),
                          "shape": list(a0.shape)}
    sched = model.noise_scheduler
    ab = sched.alphas_cumprod[int(timesteps[0])]
    numbers["noise"] = {
        "k": int(timesteps[0]), "alpha_bar": float(ab), "alphas_cumprod": tolist(
            sched.alphas_cumprod), "scheduler": type(sched).__name__,
        "beta_schedule": sched.config.beta_schedule, "clean": tolist(a0), "eps": tolist(eps[0]),
        "scaled_clean": tolist(ab.sqrt() * a0), "scaled_eps": tolist((1 - ab).sqrt() * eps[0]),
        "noisy": tolist(noisy[0]),
        "add_noise_check": float((noisy[0] - ab.sqrt() * a0 - (1 - ab).sqrt() * eps[0])
                                 .abs().max())}
    step_enc = [hooks.out[f"step_encoder.{i}"]
                for i in range(len(model.unet.diffusion_step_encoder))]
    numbers["timestep"] = {
        "layers": [{"name": type(m).__name__ + (f"({m.in_features}→{m.out_features})"
                                                if isinstance(m, torch.nn.Linear) else
                                                f"({getattr(m, 'dim', '')})"),
                    "shape": list(t.shape[1:])}
                   for m, t in zip(model.unet.diffusion_step_encoder, step_enc, strict=True)],
        "sinusoidal": tolist(step_enc[0][0]), "embedding": tolist(step_enc[-1][0, :8]),
        "embedding_shape": list(step_enc[-1].shape[1:]),
        "full_cond_shape": list(hooks.out["film_in"].shape[1:]),
        "film_out_shape": list(hooks.out["film_out"].shape[1:])}
    numbers["unet"] = {"blocks": [
        {"name": name, "type": type(model.unet.get_submodule(name)).__name__,
         "in": list(args[0][0].shape[1:]), "out": list(out.shape[1:])}
        for name, args, out in hooks.calls if name != "unet"],
        "input": list(noisy.shape[1:]), "output": list(pred.shape[1:])}
    sq = (pred[0] - eps[0]) ** 2
    numbers["loss"] = {"mse": float(loss), "pred": tolist(pred[0]), "eps": tolist(eps[0]),
                       "squared_errors": tolist(sq), "per_joint": tolist(sq.mean(0)),
                       "mean_of_squares": float(sq.mean()),
                       "masked": bool(cfg.do_mask_loss_for_padding), "mode": "eval (centre crop)"}
    numbers["sampling"] = _sample(policy, post, batch, raw, gen)
    return numbers, images, batch, eps


def _sample(policy: Any, post: Any, batch: dict, raw: dict, gen: torch.Generator
            ) -> dict[str, Any]:
    """One `predict_action_chunk` with recorded U-Net calls and the full denoised chunk."""
    cfg, model = policy.config, policy.diffusion
    noise = torch.randn((1, cfg.horizon, cfg.action_feature.shape[0]), generator=gen)
    full: list[torch.Tensor] = []
    original = model.conditional_sample

    def recording(*args: Any, **kwargs: Any) -> torch.Tensor:
        result = original(*args, **kwargs)
        full.append(result.detach().clone())
        return result

    policy.reset()
    model.conditional_sample = recording
    try:
        with Hooks() as hooks:
            hooks.every_call("unet", model.unet)
            executed = policy.predict_action_chunk({k: v for k, v in batch.items()
                                                    if k != "action"}, noise=noise)
    finally:
        del model.conditional_sample
    calls = [c for c in hooks.calls if c[0] == "unet"]
    xs = [c[1][0][0] for c in calls] + [full[0]]
    n_exec = executed.shape[1]
    start = next((s for s in range(full[0].shape[1] - n_exec + 1)
                  if torch.equal(full[0][:, s:s + n_exec], executed)), None)
    if start is None:
        raise ExplainError("predict_action_chunk returned actions that are not rows of the "
                           "sampled chunk; this lerobot version is not supported by explain")
    samples = [tolist(post(x.clone())[0]) for x in xs]
    gt = np.asarray(raw["action"][0])
    final = np.asarray(samples[-1])
    pad = np.asarray(raw["action_is_pad"][0])
    rows = slice(start, start + n_exec)
    valid = ~pad[rows]
    diff = (final[rows] - gt[rows])[valid]

    def rough(a: np.ndarray) -> list[float]:
        return np.sqrt(np.mean(np.diff(a, 2, axis=0) ** 2, axis=0)).tolist()

    return {"timesteps": [int(c[1][0][1].flatten()[0]) for c in calls],
            "samples": samples, "samples_normalised": [tolist(x[0]) for x in xs],
            "eps_pred": [tolist(c[2][0]) for c in calls], "executed": [start, start + n_exec],
            "executed_actions": tolist(post(executed.clone())[0]),
            "ground_truth": gt.tolist(),
            "rmse_executed": (np.sqrt(np.mean(diff ** 2, axis=0)).tolist()
                              if len(diff) else None),
            "roughness_sample": rough(final), "roughness_ground_truth": rough(gt),
            "scheduler": type(model.noise_scheduler).__name__,
            "num_inference_steps": len(calls),
            "final_abs_max_normalised": float(full[0].abs().max()),
            "nan": bool(math.isnan(float(full[0].sum())))}
