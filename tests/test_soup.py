"""soup.py (benchmarks/baselines): the mean of checkpoints' weights, and what it refuses."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file
from tiny_policy import make_tiny_diffusion_checkpoint

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "baselines" / "soup.py"


def _soup(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True,
                          text=True, timeout=120)


def test_the_soup_is_the_mean_of_its_ingredients_and_names_them(tmp_path: Path):
    a = make_tiny_diffusion_checkpoint(tmp_path / "a", seed=0)
    b = make_tiny_diffusion_checkpoint(tmp_path / "b", seed=1)
    out = _soup(a, b, "--out", tmp_path / "soup")
    assert out.returncode == 0, out.stderr
    wa, wb = load_file(a / "model.safetensors"), load_file(b / "model.safetensors")
    mean = load_file(tmp_path / "soup" / "model.safetensors")
    assert mean.keys() == wa.keys()
    moved = [k for k in wa if wa[k].is_floating_point() and not torch.equal(wa[k], wb[k])]
    assert moved
    for key in moved:
        assert torch.equal(mean[key], ((wa[key].double() + wb[key].double()) / 2).float())
    side = json.loads((tmp_path / "soup" / "so101_sim_train.json").read_text())
    assert [s["path"] for s in side["soup"]] == [str(a.resolve()), str(b.resolve())]
    assert side["weights"] == "mean of 2 checkpoints' weights"
    assert (tmp_path / "soup" / "policy_preprocessor.json").is_file()


def test_another_architecture_or_an_existing_out_is_refused(tmp_path: Path):
    a = make_tiny_diffusion_checkpoint(tmp_path / "a")
    other = make_tiny_diffusion_checkpoint(tmp_path / "other", input_size=(96, 128))
    out = _soup(a, other, "--out", tmp_path / "soup")
    assert out.returncode != 0 and "config.json differs" in out.stderr
    assert not (tmp_path / "soup").exists()
    out = _soup(a, a, "--out", tmp_path / "a")
    assert out.returncode != 0 and "exists; give a new folder" in out.stderr
