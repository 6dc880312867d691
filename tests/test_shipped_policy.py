"""Every shipped baseline checkpoint (policy/baselines.toml): it loads through lerobot, and its
success rate on its task has not regressed against the rate the harness measured when it was
exported."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from so101_sim.harness.baselines import baselines
from so101_sim.harness.stats import wilson_interval
from so101_sim.testing import assert_success_rate
from so101_sim.utils.paths import policy_dir

SHIPPED = sorted((task, policy_dir() / entry["checkpoint"])
                 for task, entry in baselines().items() if "checkpoint" in entry)
pytestmark = pytest.mark.skipif(
    not any((folder / "model.safetensors").is_file() for _, folder in SHIPPED),
    reason="no shipped checkpoint under policy/")


def _recorded(task: str, folder: Path) -> dict:
    """The harness result `so101-sim export --eval` stored beside the weights, for `task`."""
    info = json.loads((folder / "eval_info.json").read_text())
    assert info["config"]["task"] == task, (
        f"{folder}/eval_info.json was measured on {info['config']['task']!r}, not {task!r}: "
        "export the checkpoint with an eval of the task baselines.toml gives it")
    return info


@pytest.mark.parametrize(("task", "folder"), SHIPPED, ids=[t for t, _ in SHIPPED])
def test_shipped_policy_loads_fp32_through_lerobot(task: str, folder: Path) -> None:
    import torch
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    policy = DiffusionPolicy.from_pretrained(folder)
    dtypes = {p.dtype for p in policy.parameters()}
    assert dtypes == {torch.float32}
    n_bytes = sum(f.stat().st_size for f in folder.iterdir() if f.is_file())
    assert n_bytes <= 30 * 2**20, f"shipped checkpoint is {n_bytes / 2**20:.1f} MiB"
    card = (folder / "README.md").read_text()
    agg = _recorded(task, folder)["aggregated"]
    assert f"{agg['pc_success']:.1f}%" in card  # the card shows the measured number


@pytest.mark.parametrize(("task", "folder"), SHIPPED, ids=[t for t, _ in SHIPPED])
def test_shipped_policy_success_rate_regression(task: str, folder: Path) -> None:
    """24 of the recorded evaluation seeds, tested against the lower end of the recorded
    rate's Wilson interval (the baseline's own noise cannot fail CI) at alpha 0.01."""
    info = _recorded(task, folder)
    agg = info["aggregated"]
    baseline = wilson_interval(agg["n_success"], agg["n_episodes"])[0]
    if baseline <= 0.0:
        pytest.fail(f"recorded rate {agg['n_success']}/{agg['n_episodes']} leaves no baseline "
                    "to test against; re-export with a policy that succeeds")
    check = assert_success_rate(str(folder), task=task, baseline=baseline, episodes=24,
                                n_envs=8, seed_start=info["config"]["seed_start"])
    assert check.n == 24
