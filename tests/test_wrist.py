"""The wrist camera through the pipeline: recorded, widened into from two cameras, evaluated."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from so101_sim.cli import main
from so101_sim.record import record

sys.path.insert(0, str(Path(__file__).parent))
from tiny_policy import make_tiny_diffusion_checkpoint, short_task

THREE = ("front", "side", "wrist")


def test_record_the_wrist_camera_and_evaluate_a_policy_that_reads_it(tmp_path: Path) -> None:
    """`record --cameras front,side,wrist` stores three videos that lerobot decodes, a resume
    keeps them, and `eval` renders the wrist for a checkpoint that has a wrist input."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    task = short_task(tmp_path, max_steps=32)
    root = tmp_path / "ds"
    record(root, 1, task=task, image_size=(48, 64), cameras=THREE, keep_failures=True,
           progress=False)
    record(root, 2, task=task, image_size=(48, 64), keep_failures=True, resume=True,
           progress=False)  # no --cameras: the dataset's own
    with pytest.raises(ValueError, match=r"records cameras front,side,wrist, not front,side; "
                                         r"resume with --cameras front,side,wrist"):
        record(root, 3, task=task, image_size=(48, 64), cameras=("front", "side"),
               resume=True, progress=False)
    ds = LeRobotDataset("local/wrist", root=root)
    assert ds.meta.video_keys == [f"observation.images.{c}" for c in THREE]
    assert ds.meta.total_episodes == 2
    item = ds[40]
    wrist, front = item["observation.images.wrist"], item["observation.images.front"]
    assert wrist.shape == (3, 48, 64) and float((wrist - front).abs().mean()) > 0.05

    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "ckpt", cameras=THREE,
                                          dataset_image_size=None)
    assert main(["eval", "--policy", str(ckpt), "--task", str(task), "--episodes", "1",
                 "--n-envs", "1", "--videos", "0", "--out", str(tmp_path / "ev")]) == 0
    info = json.loads((tmp_path / "ev" / "eval_info.json").read_text())
    assert len(info["per_episode"]) == 1


def _batch(n_cams: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
    return {"observation.state": torch.randn(3, 2, 6, generator=gen),
            "observation.images": torch.rand(3, 2, n_cams, 3, 48, 64, generator=gen)}


def test_a_two_camera_checkpoint_widens_to_three_without_changing_its_actions(
        tmp_path: Path, capsys) -> None:
    """--init-from a front+side checkpoint into a front+side+wrist policy: the wrist's
    conditioning columns start at zero, so the actions are the checkpoint's whatever the wrist
    shows, and the loss has a gradient on those columns, so training can use the new view."""
    from so101_sim.train.checkpoint import init_weights_from, load_config, load_weights
    from so101_sim.train.widen import COND_SUFFIX

    two = make_tiny_diffusion_checkpoint(tmp_path / "two")
    three = make_tiny_diffusion_checkpoint(tmp_path / "three", cameras=THREE, seed=1)
    old = load_weights(load_config(two), two)
    new = load_weights(load_config(three), three)
    started = init_weights_from(new, two)
    assert started["added_cameras"] == ["observation.images.wrist"]
    assert "without the wrist camera; it enters the U-Net's conditioning through zero" in (
        capsys.readouterr().out)

    gen = torch.Generator().manual_seed(0)
    batch = _batch(2, gen)
    noise = torch.randn(3, 16, 6, generator=gen)
    with torch.no_grad():
        want = old.diffusion.generate_actions(batch, noise=noise)
        for _ in range(2):  # any wrist image: the same actions
            wide = {**batch, "observation.images": torch.cat(
                [batch["observation.images"], torch.rand(3, 2, 1, 3, 48, 64, generator=gen)], 2)}
            got = new.diffusion.generate_actions(wide, noise=noise)
            np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=0, atol=1e-5)

    # per obs step: state 6, front 16, side 16, wrist 16 (8 keypoints x 2); embed 16 first
    layers = [(n, m) for n, m in new.diffusion.named_modules()
              if f"{n}.1.weight".endswith(COND_SUFFIX)]
    assert len(layers) >= 4
    wrist_cols = [16 + t * 54 + 38 + i for t in range(2) for i in range(16)]
    for _, module in layers:
        assert torch.count_nonzero(module[1].weight[:, wrist_cols]) == 0
    new.train()
    loss = new.diffusion.compute_loss({**wide, "action": torch.randn(3, 16, 6, generator=gen),
                                       "action_is_pad": torch.zeros(3, 16, dtype=torch.bool)})
    loss.backward()
    assert all(float(m[1].weight.grad[:, wrist_cols].abs().sum()) > 0 for _, m in layers)
