"""The shipped diffusion checkpoint: it loads through lerobot, and its success rate has not
regressed against the rate the harness measured when it was exported."""

from __future__ import annotations

import json

import pytest

from so101_sim.harness.stats import wilson_interval
from so101_sim.testing import assert_success_rate
from so101_sim.utils.paths import shipped_policy_dir

SHIPPED = shipped_policy_dir()
pytestmark = pytest.mark.skipif(not (SHIPPED / "model.safetensors").is_file(),
                                reason=f"no shipped checkpoint at {SHIPPED}")


def _recorded() -> dict:
    """The harness result `so101-sim export --eval` stored beside the weights."""
    return json.loads((SHIPPED / "eval_info.json").read_text())


def test_shipped_policy_loads_fp32_through_lerobot():
    import torch
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    policy = DiffusionPolicy.from_pretrained(SHIPPED)
    dtypes = {p.dtype for p in policy.parameters()}
    assert dtypes == {torch.float32}
    n_bytes = sum(f.stat().st_size for f in SHIPPED.iterdir() if f.is_file())
    assert n_bytes <= 30 * 2**20, f"shipped checkpoint is {n_bytes / 2**20:.1f} MiB"
    card = (SHIPPED / "README.md").read_text()
    agg = _recorded()["aggregated"]
    assert f"{agg['pc_success']:.1f}%" in card  # the card shows the measured number


def test_shipped_policy_success_rate_regression():
    """24 of the recorded evaluation seeds, tested against the lower end of the recorded
    rate's Wilson interval (the baseline's own noise cannot fail CI) at alpha 0.01."""
    info = _recorded()
    agg = info["aggregated"]
    baseline = wilson_interval(agg["n_success"], agg["n_episodes"])[0]
    if baseline <= 0.0:
        pytest.fail(f"recorded rate {agg['n_success']}/{agg['n_episodes']} leaves no baseline "
                    "to test against; re-export with a policy that succeeds")
    check = assert_success_rate(str(SHIPPED), baseline=baseline, episodes=24, n_envs=8,
                                seed_start=info["config"]["seed_start"])
    assert check.n == 24
