"""probe_cube.py (benchmarks/baselines): a linear probe of an encoder's view of the cube."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from script_loader import load_script
from tiny_policy import make_tiny_diffusion_checkpoint

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "baselines" / "probe_cube.py"


def test_held_out_errors_find_a_linear_signal_and_not_noise():
    probe = load_script(SCRIPT)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 20))
    y = x[:, :2] @ np.array([[0.02, 0.0], [0.0, 0.03]])  # metres, exactly linear in x
    assert np.median(probe.cv_errors(x, y)) < 0.002
    noise = rng.normal(size=(300, 20))  # features that say nothing about y
    assert np.median(probe.cv_errors(noise, y)) > 10 * np.median(probe.cv_errors(x, y))


def test_the_table_has_a_row_per_probe_and_camera(tmp_path: Path):
    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "tiny", dataset_image_size=None)
    out = subprocess.run([sys.executable, str(SCRIPT), str(ckpt), "--seeds", "8", "--bins",
                          "2", "--render", "48x64", "--per-camera", "--random"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    rows = [r for r in out.stdout.splitlines() if r.startswith("| tiny") or
            r.startswith("| random")]
    assert len(rows) == 2 * 2 * 3  # (checkpoint, random) x (reset, approach) x (both, each)
    assert all(len(r.split("|")) == 5 + 2 for r in rows)  # name, probe, 2 bins, all


def test_keypoints_are_what_the_encoders_linear_layer_reads(tmp_path: Path):
    import torch

    from so101_sim.harness.policies.lerobot import LeRobotPolicy

    probe = load_script(SCRIPT)
    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "tiny", dataset_image_size=None)
    enc = LeRobotPolicy(ckpt, batch_size=1, log=lambda s: None).policy.diffusion.rgb_encoder
    x = torch.rand(3, 3, 48, 64)
    with torch.no_grad():
        points, full = probe.Keypoints(enc)(x), enc(x)
    assert points.shape == (3, enc.out.in_features)  # 2 per keypoint, before the linear layer
    assert torch.allclose(enc.relu(enc.out(points)), full)


def test_a_wrong_checkpoint_path_fails_before_any_render(tmp_path: Path, monkeypatch):
    probe = load_script(SCRIPT)

    def no_render(*args, **kwargs):
        raise AssertionError("rendered before checking the checkpoints")
    monkeypatch.setattr(probe, "collect", no_render)
    with pytest.raises(SystemExit, match=r"^probe_cube: policy checkpoint .*gone not found; "):
        probe.main([str(tmp_path / "gone")])
