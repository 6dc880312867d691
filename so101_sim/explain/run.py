"""`so101-sim explain`: the seed walkthrough, re-run on your own dataset and checkpoint.

One training example (an episode and frame of a LeRobotDataset, read with lerobot's own
delta_timestamps windowing) goes through the policy's real modules: its saved (or freshly built)
normaliser, one `policy.forward` for the loss and one `policy.predict_action_chunk` for a
sampled chunk (`explain.trace` records them). So every number on the page is what lerobot
computes for this batch, and shapes are read, never assumed: the page is right for the `cpu`
preset, the `seed` preset or any other diffusion config. `explain.page` renders the page.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from so101_sim.dataset.reader import NotADatasetError, open_lerobot_dataset
from so101_sim.explain.errors import ExplainError
from so101_sim.explain.hooks import tolist
from so101_sim.explain.trace import STATE_KEY, trace
from so101_sim.train.checkpoint import checkpoint_name, load_checkpoint, read_train_info
from so101_sim.train.demos import normalization_stats
from so101_sim.train.presets import load_preset, make_config, policy_features
from so101_sim.utils.atomic import write_json_atomic, write_text_atomic
from so101_sim.utils.locks import hold_folder, lock_scope
from so101_sim.utils.paths import foreign_folder
from so101_sim.utils.trust import UntrustedCheckpointError


@dataclass
class Explanation:
    """The page's numbers (JSON-ready), its images, and the objects that produced them."""

    numbers: dict[str, Any]
    images: dict[str, np.ndarray]      # "<camera>/<orig|policy>/<obs step>" -> uint8 [H, W, 3]
    policy: Any = field(repr=False)    # the DiffusionPolicy, in eval mode
    batch: dict[str, Any] = field(repr=False)  # the preprocessed batch that policy.forward saw
    noise: Any = field(repr=False)     # epsilon handed to compute_loss, [1, horizon, action_dim]
    html_path: Path | None = None
    json_path: Path | None = None


# ----------------------------------------------------------------------------- loading


def _open_dataset(path: Path, delta_timestamps: dict[str, list[float]] | None = None) -> Any:
    try:
        return open_lerobot_dataset(path, delta_timestamps=delta_timestamps)
    except NotADatasetError as exc:
        raise ExplainError(str(exc)) from None


def _load_checkpoint(path: Path) -> tuple[Any, Any, Any, dict[str, Any]]:
    """The checkpoint's policy and saved processors; refuses processor files that import code."""
    try:
        _, policy, pre, post = load_checkpoint(path, "cpu", expect_type="diffusion")
    except UntrustedCheckpointError:
        raise
    except (FileNotFoundError, ValueError, RuntimeError) as exc:
        raise ExplainError(f"--policy {str(path)!r}: {exc} (explain follows Diffusion Policy "
                           "and needs a 'diffusion' checkpoint)") from None
    info: dict[str, Any] = {"source": "checkpoint", "path": str(path),
                            "name": checkpoint_name(path)}
    with contextlib.suppress(OSError, ValueError, AttributeError):
        train = read_train_info(path) or {}
        info["trained"] = {k: train.get(k) for k in ("preset", "step", "dataset_episodes",
                                                     "last_loss", "weights")}
    return policy, pre, post, info


def _fresh_policy(dataset: Any, preset_name: str, seed: int) -> tuple[Any, Any, Any, dict]:
    """An untrained preset policy with the dataset's normalisation stats, as `train` builds it."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    preset = load_preset(preset_name)
    if preset.policy_type != "diffusion":
        raise ExplainError(f"--preset {preset_name} is an {preset.policy_type!r} preset; "
                           "explain follows Diffusion Policy: give a diffusion preset (e.g. "
                           "seed, cpu) or a diffusion --policy")
    cams = tuple(k.split(".")[-1] for k in dataset.meta.video_keys)
    cfg = make_config(preset, *policy_features(preset.image_size, cams,
                                               dataset.meta.features["action"]["shape"][0]))
    cfg.device = "cpu"
    torch.manual_seed(seed)
    policy = DiffusionPolicy(cfg)
    pre, post = make_pre_post_processors(cfg, dataset_stats=normalization_stats(dataset, preset))
    return policy, pre, post, {"source": "fresh preset (untrained)", "name":
                               f"{preset.name}-untrained", "path": str(preset.path)}


# ----------------------------------------------------------------------------- main


@lock_scope
def explain(dataset_dir: str | Path, policy_path: str | Path | None = None, episode: int = 0,
            frame: int = 5, k: int = 25, out: str | Path | None = None,
            preset: str | None = None, seed: int = 0, write: bool = True) -> Explanation:
    """Trace frame `frame` of episode `episode` through the policy; write explain.html/.json.

    Without `policy_path` the policy is a fresh, untrained `preset` with the dataset's
    normalisation stats (default ``seed``). `seed` fixes the noise of the loss and of the
    DDIM sampling.
    """
    if policy_path is not None and preset is not None:
        raise ExplainError(f"--preset {preset} given with --policy: a checkpoint brings its "
                           "own config; drop --preset (it builds the untrained policy traced "
                           "when there is no --policy)")
    if out is not None and write:  # before anything loads
        if Path(out).is_file():
            raise ExplainError(f"--out {out} is a file; expected a folder for explain.html and "
                               "explain.json: choose another --out")
        if (what := foreign_folder(Path(out))) is not None:
            raise ExplainError(f"--out {out} {what}; the page and its numbers would go among "
                               "its files: choose another --out")
    dataset_dir = Path(dataset_dir)
    meta_ds = _open_dataset(dataset_dir)
    meta = meta_ds.meta
    if not 0 <= episode < meta.total_episodes:
        raise ExplainError(f"--episode {episode} is out of range; {dataset_dir} holds episodes "
                           f"0..{meta.total_episodes - 1}")
    row = meta.episodes[episode]
    lo, hi = int(row["dataset_from_index"]), int(row["dataset_to_index"])
    if not 0 <= frame < hi - lo:
        raise ExplainError(f"--frame {frame} is out of range; episode {episode} has frames "
                           f"0..{hi - lo - 1}")
    if policy_path is not None:
        policy, pre, post, info = _load_checkpoint(Path(policy_path))
    else:
        policy, pre, post, info = _fresh_policy(meta_ds, preset or "seed", seed)
    cfg = policy.config
    if not 0 <= k < cfg.num_train_timesteps:
        raise ExplainError(f"--k {k} is out of range; the scheduler has steps "
                           f"0..{cfg.num_train_timesteps - 1}")
    missing = [key for key in cfg.input_features if key not in meta.features]
    if missing:
        raise ExplainError(f"the policy needs {missing}, which {dataset_dir} does not record; "
                           f"it has {sorted(meta.features)}")
    dest = Path(out) if out else Path("outputs/explain") / f"{info['name']}-ep{episode}-f{frame}"
    if write:  # one writer per folder, from here to the end
        hold_folder(dest, "the explanation", again="rerun")
    policy.eval()
    policy.reset()
    fps = meta.fps
    delta = {key: [i / fps for i in cfg.observation_delta_indices] for key in cfg.input_features}
    delta["action"] = [i / fps for i in cfg.action_delta_indices]
    item = _open_dataset(dataset_dir, delta)[lo + frame]

    numbers, images, batch, eps = trace(policy, pre, post, item, k=k, seed=seed)
    names = meta.features[STATE_KEY].get("names") or [f"joint {i}" for i in range(6)]
    numbers["meta"] = {
        "dataset": str(dataset_dir), "episodes": meta.total_episodes,
        "frames": meta.total_frames, "fps": fps, "cameras": list(cfg.image_features),
        "dataset_image_size": list(meta.features[meta.video_keys[0]]["shape"][:2])
        if meta.video_keys else None,
        "episode": episode, "frame": frame, "episode_length": hi - lo, "global_index": lo + frame,
        "obs_frames": [frame + d for d in cfg.observation_delta_indices],
        "obs_timestamps": [(frame + d) / fps for d in cfg.observation_delta_indices],
        "action_frames": [frame + d for d in cfg.action_delta_indices],
        "k": k, "seed": seed, "joint_names": list(names), "policy": info,
        "parameters": sum(p.numel() for p in policy.parameters()),
        "config": {key: tolist(getattr(cfg, key)) for key in (
            "n_obs_steps", "horizon", "n_action_steps", "crop_shape", "crop_is_random",
            "vision_backbone", "use_group_norm", "spatial_softmax_num_keypoints",
            "use_separate_rgb_encoder_per_camera", "down_dims", "kernel_size", "n_groups",
            "diffusion_step_embed_dim", "use_film_scale_modulation", "noise_scheduler_type",
            "num_train_timesteps", "beta_schedule", "prediction_type", "clip_sample",
            "num_inference_steps", "do_mask_loss_for_padding")},
    }
    result = Explanation(numbers, images, policy, batch, eps)
    if write:
        from so101_sim.explain.page import render_page

        dest.mkdir(parents=True, exist_ok=True)
        result.json_path = dest / "explain.json"
        write_json_atomic(result.json_path, numbers, indent=1)
        result.html_path = dest / "explain.html"
        write_text_atomic(result.html_path, render_page(numbers, images))
    return result
