"""What training reads from a recorded dataset: states, actions, frames and episode bounds in
memory (`DemoArrays`), batches gathered from them with lerobot's padding rules, the
normalisation stats, and which frames a batch is drawn from (`sample_weights`: uniform, or more
often near the gripper's closes)."""

from __future__ import annotations

import math
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from so101_sim.dataset.reader import read_frames
from so101_sim.train.frame_cache import load_frames
from so101_sim.train.presets import Preset, available_presets, load_preset
from so101_sim.train.state import TrainError

if TYPE_CHECKING:  # annotations only: lerobot loads when a dataset is opened
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class DemoArrays:
    """Everything training reads, in memory: states, actions, frames and episode bounds."""

    state: np.ndarray                 # [N, 6] float32
    action: np.ndarray                # [N, 6] float32
    frames: dict[str, np.ndarray]     # camera key -> uint8 [N, 3, h, w]
    episode_from: np.ndarray          # [N] first index of each frame's episode
    episode_to: np.ndarray            # [N] one past its last index
    starts: np.ndarray                # frame indices a sample may be centred on


def load_demos(dataset: LeRobotDataset, preset: Preset, cache_dir: Path | None) -> DemoArrays:
    """Read a LeRobotDataset into `DemoArrays` for `preset` (frames resized to its image size)."""
    hf = dataset.hf_dataset.with_format("numpy")
    state = np.asarray(hf["observation.state"], dtype=np.float32)
    action = np.asarray(hf["action"], dtype=np.float32)
    index = np.asarray(hf["index"])
    if not np.array_equal(index, np.arange(len(index))):
        raise TrainError(f"dataset {dataset.meta.root}: frame indices are not 0..N-1 in order; "
                         "train on a dataset written by `so101-sim record` or lerobot")
    ep_from, ep_to = np.empty((2, len(index)), dtype=np.int64)
    starts = []
    drop = int(preset.policy.get("drop_n_last_frames", 0))  # ACT samples every frame
    for row in dataset.meta.episodes:
        lo, hi = int(row["dataset_from_index"]), int(row["dataset_to_index"])
        ep_from[lo:hi], ep_to[lo:hi] = lo, hi
        starts.append(np.arange(lo, max(lo + 1, hi - drop)))
    frames = load_frames(dataset, preset.image_size, cache_dir)
    return DemoArrays(state, action, frames, ep_from, ep_to, np.concatenate(starts))


def gather_batch(demos: DemoArrays, idx: np.ndarray, obs_offsets: list[int] | None,
                 act_offsets: list[int]) -> dict:
    """A training batch centred on frames `idx`, padded at episode edges as lerobot does.

    The offsets are the config's `observation_delta_indices` and `action_delta_indices`
    (Diffusion: observations t-n_obs+1..t, actions from t-n_obs+1 on; ACT: None, the frame t
    alone with no time axis, and actions t..t+chunk-1). Indices outside the episode repeat its
    edge frame and are flagged in `action_is_pad`.
    """
    lo, hi = demos.episode_from[idx, None], demos.episode_to[idx, None] - 1
    obs_i = np.clip(idx[:, None] + np.asarray(obs_offsets or [0])[None], lo, hi)
    if obs_offsets is None:
        obs_i = obs_i[:, 0]  # one frame, no time axis
    act_raw = idx[:, None] + np.asarray(act_offsets)[None]
    act_i = np.clip(act_raw, lo, hi)
    batch: dict[str, Any] = {
        "observation.state": torch.from_numpy(demos.state[obs_i]),
        "action": torch.from_numpy(demos.action[act_i]),
        "action_is_pad": torch.from_numpy((act_raw < lo) | (act_raw > hi)),
    }
    for key, arr in demos.frames.items():
        batch[key] = torch.from_numpy(arr[obs_i]).float().div_(255.0)
    return batch


def normalization_stats(dataset: LeRobotDataset, preset: Preset
                        ) -> dict[str, dict[str, torch.Tensor]]:
    """State/action stats from the dataset; pixel mean/std per the preset."""
    stats: dict[str, dict[str, torch.Tensor]] = {}
    for key in ("observation.state", "action"):
        stats[key] = {k: torch.as_tensor(np.asarray(v), dtype=torch.float32)
                      for k, v in dataset.meta.stats[key].items()}
    for key in dataset.meta.video_keys:
        if preset.image_normalize == "imagenet":
            mean, std = torch.tensor(IMAGENET_MEAN), torch.tensor(IMAGENET_STD)
        else:
            mean = torch.as_tensor(np.asarray(dataset.meta.stats[key]["mean"])).reshape(3)
            std = torch.as_tensor(np.asarray(dataset.meta.stats[key]["std"])).reshape(3)
        stats[key] = {"mean": mean.reshape(3, 1, 1).float(), "std": std.reshape(3, 1, 1).float()}
    return stats


@dataclass(frozen=True)
class CloseWeighting:
    """Draw batch centres `factor` times as often in a window around each close of the gripper.

    A close is the gripper's action falling below `closed_below` after it was above
    `open_above` (the expert opens to ~45 to approach and shuts to 0 on the cube). The window
    runs from `before` frames ahead of the close (the final approach) to `after` frames past it
    (the lift that shows whether the cube came along). For tasks whose misses are imprecise
    grasps (tidy's second and third cube), so the policy sees those frames more often.
    """

    factor: float
    before: int = 45
    after: int = 15
    open_above: float = 30.0
    closed_below: float = 10.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.factor) and self.factor >= 1):
            raise TrainError(f"--oversample-closes {self.factor}: expected a factor >= 1 "
                             "(1 = every frame alike; 3 draws frames near a close 3x as often)")


def close_windows(grip: np.ndarray, episode_from: np.ndarray, episode_to: np.ndarray,
                  w: CloseWeighting) -> np.ndarray:
    """A bool per frame: inside the window of a close of its own episode."""
    mask = np.zeros(len(grip), dtype=bool)
    for lo, hi in np.unique(np.stack([episode_from, episode_to], 1), axis=0):
        opened = False
        for t in range(lo, hi):
            if grip[t] > w.open_above:
                opened = True
            elif grip[t] < w.closed_below and opened:
                opened = False
                mask[max(lo, t - w.before):min(hi, t + w.after + 1)] = True
    return mask


def sample_weights(demos: DemoArrays, action_names: list[str],
                   weighting: CloseWeighting | None) -> np.ndarray | None:
    """Probabilities over `demos.starts` for `numpy.random.Generator.choice`, or None (uniform)."""
    if weighting is None or weighting.factor == 1:
        return None
    grip = [i for i, n in enumerate(action_names) if n.split(".")[0] == "gripper"]
    if len(grip) != 1:
        raise TrainError(f"--oversample-closes needs one gripper action; the dataset's actions "
                         f"are named {action_names}; expected one named 'gripper' or "
                         "'gripper.pos' (drop the flag for this dataset)")
    near = close_windows(demos.action[:, grip[0]], demos.episode_from, demos.episode_to,
                         weighting)[demos.starts]
    if not near.any():
        raise TrainError("--oversample-closes: no close of the gripper in the dataset's actions "
                         f"(below {weighting.closed_below} after above {weighting.open_above}); "
                         "drop the flag, or check the dataset holds grasps")
    w = np.where(near, weighting.factor, 1.0)
    return w / w.sum()


def failed_episodes(root: Path, features: dict[str, Any]) -> list[int]:
    """Indices of the episodes whose ``episode_success`` is false (rollouts of ``eval
    --save-rollouts`` keep every outcome); [] for a dataset without that column."""
    if "episode_success" not in features:
        return []
    df = read_frames(Path(root), ["episode_index", "episode_success"])
    first = df.groupby("episode_index")["episode_success"].first()
    return [int(i) for i, ok in first.items() if not bool(np.asarray(ok).reshape(-1)[0])]


def failures_note(root: Path, repo_id: str, failed: list[int], total: int) -> str | None:
    """One line when the demos include failed episodes, with lerobot's command to drop them."""
    if not failed:
        return None
    ok = shlex.quote(f"{Path(root)}_ok")
    return (f"so101-sim train: note: {len(failed)} of {total} episodes in {root} failed "
            "(episode_success false: rollouts keep every outcome) and are imitated like the "
            "rest; to train on the successes only: lerobot-edit-dataset --repo_id "
            f"{shlex.quote(repo_id)} --root {shlex.quote(str(root))} --new_repo_id "
            f"{shlex.quote(f'{repo_id}_ok')} --new_root {ok} "
            f"--operation.type delete_episodes --operation.episode_indices '{failed}'")


def frames_note(recorded: tuple[int, int], preset: Preset) -> str | None:
    """One line when the recorded frames are smaller than the preset's input (upscaled: no
    detail is gained) or of another aspect ratio (stretched): both train without error."""
    (h, w), (ph, pw) = recorded, preset.image_size
    if abs(h / w - ph / pw) > 0.02:
        return (f"so101-sim train: note: the dataset's frames are {h}x{w} and preset "
                f"{preset.name}'s input {ph}x{pw}, another aspect ratio: every frame is "
                f"stretched to {ph}x{pw}; record at the preset's aspect (so101-sim record "
                f"--image-size {h}x{round(h * pw / ph)}) for undistorted frames")
    if h >= ph and w >= pw:
        return None
    fits = [n for n in available_presets() if n != preset.name
            and (s := load_preset(n)).policy_type == preset.policy_type
            and s.image_size[0] <= h and s.image_size[1] <= w]
    other = f", or train a preset made for {h}x{w} or less ({', '.join(fits)})" if fits else ""
    return (f"so101-sim train: note: the dataset's frames are {h}x{w}, smaller than preset "
            f"{preset.name}'s {ph}x{pw} input: they are upscaled, which adds no detail; record "
            f"at {ph}x{pw} or larger (so101-sim record --image-size, default 480x640){other}")


def demos_notes(root: Path, dataset: Any, preset: Preset) -> list[str]:
    """The lines `train` prints about its demos before the first step: frames smaller than
    or shaped unlike the preset's input, and failed episodes."""
    size = tuple(dataset.meta.features[dataset.meta.video_keys[0]]["shape"][:2])
    failed = failed_episodes(root, dataset.meta.features)
    return [n for n in (frames_note(size, preset), failures_note(
        root, dataset.repo_id, failed, dataset.meta.total_episodes)) if n]
