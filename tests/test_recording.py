"""Recording expert demos as a LeRobotDataset: round trip, interruption/resume, seeds, replay."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from so101_sim.recording import DEFAULT_REPO_ID, record, replay, stored_seeds
from so101_sim.units import FEATURE_NAMES

SMALL = (48, 64)
FPS = 30


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("rec") / "ds"
    summary = record(root, 2, image_size=SMALL, progress=False)
    assert summary["episodes"] == 2 and summary["env_steps"] > 0
    return root


def _load(root: Path, **kwargs):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(DEFAULT_REPO_ID, root=root, **kwargs)


def test_dataset_loads_with_lerobot_delta_timestamps(dataset: Path) -> None:
    images = ["observation.images.front", "observation.images.side"]
    delta = {k: [-1 / FPS, 0.0] for k in [*images, "observation.state"]}
    delta["action"] = [i / FPS for i in range(16)]
    ds = _load(dataset, delta_timestamps=delta)
    assert ds.fps == FPS and ds.meta.robot_type == "so101_follower"
    assert ds.num_episodes == 2
    assert ds.meta.features["action"]["names"] == list(FEATURE_NAMES)
    assert ds.meta.features["observation.state"]["names"] == list(FEATURE_NAMES)
    for key in images:
        assert ds.meta.features[key]["dtype"] == "video"
    item = ds[5]
    assert item["observation.state"].shape == (2, 6)
    assert item["action"].shape == (16, 6)
    for key in images:
        assert item[key].shape == (2, 3, *SMALL)
    assert item["task"] == "Pick up the red cube and place it on the green target."
    assert stored_seeds(dataset) == [0, 1]
    assert torch.isfinite(item["action"]).all()


def test_replay_is_deterministic(dataset: Path) -> None:
    assert replay(dataset, 1) < 1e-4


def test_evaluation_seeds_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="evaluation range"):
        record(tmp_path / "ds", 1, seed_start=100_000, image_size=SMALL, progress=False)
    assert not (tmp_path / "ds").exists()


def test_existing_dataset_needs_resume(dataset: Path) -> None:
    with pytest.raises(ValueError, match="--resume"):
        record(dataset, 3, image_size=SMALL, progress=False)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "so101_sim.cli", *args]


def _total_episodes(root: Path) -> int:
    try:
        return json.loads((root / "meta" / "info.json").read_text())["total_episodes"]
    except (FileNotFoundError, json.JSONDecodeError, KeyError):
        return 0


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_interrupt_then_resume(tmp_path: Path, sig: signal.Signals) -> None:
    root = tmp_path / "ds"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HF_HUB_OFFLINE": "1"}
    common = ["--episodes", "4", "--out", str(root), "--image-size", "48x64"]
    proc = subprocess.Popen(_cli("record", *common), env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while _total_episodes(root) < 1 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()[1].decode()[-2000:]
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err.decode()[-2000:]

    done = _load(root).num_episodes
    assert 1 <= done < 4
    seeds = stored_seeds(root)
    assert len(seeds) == done

    out = subprocess.run(_cli("record", *common, "--resume"), env=env,
                         capture_output=True, timeout=120)
    assert out.returncode == 0, out.stderr.decode()[-2000:]
    ds = _load(root)
    assert ds.num_episodes == 4
    seeds = stored_seeds(root)
    assert len(seeds) == len(set(seeds)) == 4 and seeds[:done] == list(range(done))
    assert np.isfinite(ds[len(ds) - 1]["observation.state"].numpy()).all()


def test_diffusion_policy_loss_is_finite(dataset: Path) -> None:
    """A tiny DiffusionPolicy (seed-shaped: To=2, Tp=16) trains on a batch of the dataset."""
    from lerobot.configs.types import FeatureType
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.diffusion.processor_diffusion import make_diffusion_pre_post_processors
    from lerobot.utils.feature_utils import dataset_to_policy_features

    meta_features = _load(dataset).meta.features
    wanted = {k: v for k, v in meta_features.items()
              if k.startswith("observation.") or k == "action"}
    feats = dataset_to_policy_features(wanted)
    cfg = DiffusionConfig(
        input_features={k: f for k, f in feats.items() if f.type is not FeatureType.ACTION},
        output_features={k: f for k, f in feats.items() if f.type is FeatureType.ACTION},
        n_obs_steps=2, horizon=16, n_action_steps=8, down_dims=(16, 32),
        diffusion_step_embed_dim=16, pretrained_backbone_weights=None, use_group_norm=True,
        crop_shape=None, spatial_softmax_num_keypoints=8, num_train_timesteps=10,
        device="cpu")
    delta = {k: [i / FPS for i in v] for k, v in {
        **{k: cfg.observation_delta_indices for k in cfg.input_features},
        "action": cfg.action_delta_indices}.items()}
    ds = _load(dataset, delta_timestamps=delta)
    pre, _ = make_diffusion_pre_post_processors(cfg, dataset_stats=ds.meta.stats)
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=2, shuffle=True)))
    policy = DiffusionPolicy(cfg)
    loss, _ = policy.forward(pre(batch))
    assert torch.isfinite(loss)
    loss.backward()
