"""--init-from into a policy with more spatial-softmax keypoints per camera (train.widen)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))
from tiny_policy import make_tiny_diffusion_checkpoint


def _assert_same_actions(old, new, rows: int, size: tuple[int, int], atol: float):
    """Both policies sample the same actions from one random two-camera batch and noise;
    returns (batch, generator) for further draws."""
    gen = torch.Generator().manual_seed(0)
    batch = {"observation.state": torch.randn(rows, 2, 6, generator=gen),
             "observation.images": torch.rand(rows, 2, 2, 3, *size, generator=gen)}
    noise = torch.randn(rows, 16, 6, generator=gen)
    with torch.no_grad():
        want = old.diffusion.generate_actions(batch, noise=noise)
        got = new.diffusion.generate_actions(batch, noise=noise)
    np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=0, atol=atol)
    return batch, gen


def test_an_8_keypoint_checkpoint_widens_to_16_without_changing_its_actions(
        tmp_path: Path, capsys) -> None:
    """The new keypoints' features enter the U-Net through zero columns and the old features
    read them through zero weights: the widened policy samples the checkpoint's actions, the
    loss has a gradient on the new columns, and the new keypoints are not all alike."""
    from so101_sim.train.checkpoint import init_weights_from, load_config, load_weights
    from so101_sim.train.widen import COND_SUFFIX, KEYPOINT_CONV

    eight = make_tiny_diffusion_checkpoint(tmp_path / "eight")
    sixteen = make_tiny_diffusion_checkpoint(tmp_path / "sixteen", keypoints=16, seed=1)
    old = load_weights(load_config(eight), eight)
    new = load_weights(load_config(sixteen), sixteen)
    started = init_weights_from(new, eight)
    assert started["added_keypoints"] == 8 and "added_cameras" not in started
    assert "has 8 keypoints per camera, the preset 16; the new ones enter" in (
        capsys.readouterr().out)
    conv = new.state_dict()[KEYPOINT_CONV + "weight"]
    assert torch.equal(conv[:8], old.state_dict()[KEYPOINT_CONV + "weight"])
    assert float(conv[8:].std()) > 0  # the fresh policy's random keypoints, not zeros

    batch, gen = _assert_same_actions(old, new, rows=3, size=(48, 64), atol=1e-5)

    # per obs step: state 6, front 32, side 32 (16 keypoints x 2), the old 16 of each first
    layers = [m for n, m in new.diffusion.named_modules()
              if f"{n}.1.weight".endswith(COND_SUFFIX)]
    assert len(layers) >= 4
    new_cols = [16 + t * 70 + 6 + cam * 32 + 16 + i
                for t in range(2) for cam in range(2) for i in range(16)]
    for module in layers:
        assert torch.count_nonzero(module[1].weight[:, new_cols]) == 0
    new.train()
    loss = new.diffusion.compute_loss({**batch, "action": torch.randn(3, 16, 6, generator=gen),
                                       "action_is_pad": torch.zeros(3, 16, dtype=torch.bool)})
    loss.backward()
    assert all(float(m[1].weight.grad[:, new_cols].abs().sum()) > 0 for m in layers)


def test_fewer_keypoints_than_the_checkpoint_is_refused(tmp_path: Path) -> None:
    """Narrowing would drop learned keypoints: it is not a widening, so the strict load names
    the mismatch instead of silently cutting weights."""
    import pytest

    from so101_sim.train.checkpoint import init_weights_from, load_config, load_weights

    sixteen = make_tiny_diffusion_checkpoint(tmp_path / "sixteen", keypoints=16)
    eight = make_tiny_diffusion_checkpoint(tmp_path / "eight", seed=1)
    new = load_weights(load_config(eight), eight)
    with pytest.raises(ValueError, match=r"does not fit the preset's 'diffusion' architecture"):
        init_weights_from(new, sixteen)


def test_the_kp128_preset_widens_the_shipped_suite_policy_without_changing_its_actions(
        capsys) -> None:
    """benchmarks/baselines/presets/cpu_ft_nocrop_kp128.toml: 128 keypoints, no crop, lr 1e-4;
    the shipped 32-keypoint suite_diffusion starts it with the actions it samples through
    `cpu_ft_nocrop` (the same preset at 32 keypoints: whole frames, as this one sees them)."""
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    from so101_sim.train.checkpoint import init_weights_from
    from so101_sim.train.presets import load_preset, make_config, policy_features
    from so101_sim.utils.paths import policy_dir

    preset = load_preset(Path(__file__).parents[1] / "benchmarks" / "baselines" / "presets"
                         / "cpu_ft_nocrop_kp128.toml")
    assert preset.policy["spatial_softmax_num_keypoints"] == 128
    assert preset.policy["crop_shape"] is None and preset.policy["optimizer_lr"] == 1e-4
    shipped = policy_dir() / "suite_diffusion"
    old, new = (DiffusionPolicy(make_config(p, *policy_features(p.image_size))).eval()
                for p in (load_preset("cpu_ft_nocrop"), preset))
    assert "added_keypoints" not in init_weights_from(old, shipped)
    assert init_weights_from(new, shipped)["added_keypoints"] == 96
    _assert_same_actions(old, new, rows=2, size=(60, 80), atol=1e-4)


def test_a_checkpoint_whose_weights_disagree_with_its_config_is_refused(tmp_path: Path) -> None:
    """A checkpoint's files are data: keypoint weights that do not match its config's count
    get an error naming the tensor and both shapes, not a bare torch error or a silent cut."""
    import pytest
    from safetensors.torch import load_file, save_file

    from so101_sim.train.checkpoint import init_weights_from, load_config, load_weights
    from so101_sim.train.widen import KEYPOINT_CONV

    eight = make_tiny_diffusion_checkpoint(tmp_path / "eight")
    tensors = load_file(eight / "model.safetensors")
    tensors[KEYPOINT_CONV + "weight"] = tensors[KEYPOINT_CONV + "weight"][:4].contiguous()
    save_file(tensors, eight / "model.safetensors")
    sixteen = make_tiny_diffusion_checkpoint(tmp_path / "sixteen", keypoints=16, seed=1)
    new = load_weights(load_config(sixteen), sixteen)
    with pytest.raises(ValueError, match=r"pool\.nets\.weight is \(4, 512, 1, 1\), not the 8 "
                                         r"rows its config\.json's 8 keypoints need"):
        init_weights_from(new, eight)
