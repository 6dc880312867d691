"""Every shipped checkpoint (policy/baselines.toml's, and eval's default): it loads through
lerobot, and its success rate on each task it answers for has not regressed against the rate
the harness measured when it was exported (a multi-task checkpoint is tested once per task, on
as many seeds as that task's rate needs for the test to be able to fail)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from so101_sim.harness.baselines import baselines
from so101_sim.harness.export import recorded_eval
from so101_sim.harness.stats import critical_successes, power_below, wilson_interval
from so101_sim.tasks import DEFAULT_TASK
from so101_sim.testing import assert_success_rate
from so101_sim.utils.paths import policy_dir, shipped_policy_dir

# the baselines, and the default policy of `so101-sim eval` (pick_place_diffusion) on its task
SHIPPED = sorted({(task, policy_dir() / entry["checkpoint"])
                  for task, entry in baselines().items() if "checkpoint" in entry}
                 | {(DEFAULT_TASK, shipped_policy_dir())})
FOLDERS = sorted({folder for _, folder in SHIPPED})
pytestmark = pytest.mark.skipif(
    not any((folder / "model.safetensors").is_file() for folder in FOLDERS),
    reason="no shipped checkpoint under policy/")
ALPHA = 0.01


def _recorded(task: str, folder: Path) -> dict:
    """The harness result `so101-sim export --eval` stored beside the weights, for `task`."""
    path = recorded_eval(folder, task)
    assert path.is_file(), (f"{folder} has no eval for {task!r}: export it with one --eval "
                            "per task baselines.toml gives it")
    info = json.loads(path.read_text())
    assert info["config"]["task"] == task, (
        f"{path} was measured on {info['config']['task']!r}, not {task!r}: "
        "export the checkpoint with an eval of the task baselines.toml gives it")
    return info


def seeds_for(baseline: float, alpha: float = ALPHA, power: float = 0.9,
              most: int = 48) -> int:
    """Seeds for the one-sample test of a task: the fewest (from 24, in steps of 8) at which a
    policy whose rate fell to a quarter of `baseline` fails with `power`; at most `most` (the
    suite's time budget). At the cap the test still fails a policy that never succeeds: the
    cap is raised until 0 successes would fail."""
    n = 24
    while n < most and power_below(n, baseline, baseline / 4, alpha) < power:
        n += 8
    while critical_successes(n, baseline, alpha) < 0:  # 0/n must be able to fail
        n += 8
    return n


def test_seeds_for_sizes_the_test_so_it_can_fail() -> None:
    assert seeds_for(0.805) == 24  # pick_place's shipped lower bound: 24 seeds have power
    assert power_below(seeds_for(0.383), 0.383, 0.383 / 4, ALPHA) >= 0.9
    for low in (0.05, 0.116, 0.218):  # rare successes: the cap gives way until 0/n can fail
        n = seeds_for(low)
        assert critical_successes(n, low, ALPHA) >= 0
        assert n == 48 or critical_successes(n - 8, low, ALPHA) < 0  # no more seeds than that


@pytest.mark.parametrize("folder", FOLDERS, ids=[f.name for f in FOLDERS])
@pytest.mark.usefixtures("lerobot_tempfiles")
def test_shipped_policy_loads_fp32_through_lerobot(folder: Path) -> None:
    import torch
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    policy = DiffusionPolicy.from_pretrained(folder)
    dtypes = {p.dtype for p in policy.parameters()}
    assert dtypes == {torch.float32}
    n_bytes = sum(f.stat().st_size for f in folder.iterdir() if f.is_file())
    # the repo's limit is 30 MB (decimal; an fp16 ACT of the `act` preset is 31.1 MB, which
    # is 29.7 MiB, so the unit matters)
    assert n_bytes <= 30e6, f"shipped checkpoint is {n_bytes / 1e6:.2f} MB; the limit is 30 MB"
    card = (folder / "README.md").read_text()
    for task in (t for t, f in SHIPPED if f == folder):
        agg = _recorded(task, folder)["aggregated"]
        assert f"{agg['pc_success']:.1f}%" in card  # the card shows the measured number


@pytest.mark.parametrize(("task", "folder"), SHIPPED, ids=[f"{t}-{f.name}" for t, f in SHIPPED])
def test_shipped_policy_success_rate_regression(task: str, folder: Path) -> None:
    """The first `seeds_for` recorded evaluation seeds, tested against the lower end of the
    recorded rate's Wilson interval (the baseline's own noise cannot fail CI) at alpha 0.01."""
    info = _recorded(task, folder)
    agg = info["aggregated"]
    baseline = wilson_interval(agg["n_success"], agg["n_episodes"])[0]
    if baseline <= 0.0:
        pytest.fail(f"recorded rate {agg['n_success']}/{agg['n_episodes']} leaves no baseline "
                    "to test against; re-export with a policy that succeeds")
    n = seeds_for(baseline)
    # 8 envs, one forward at a time: CI runs two tests at once, so a second forward thread
    # only competes with the other test, and more episodes in flight are lost at the early
    # stop (16 envs: 145 s against 185 s alone, but 583 against <= 464 s of test time in CI).
    check = assert_success_rate(str(folder), task=task, baseline=baseline, episodes=n,
                                n_envs=8, seed_start=info["config"]["seed_start"])
    assert check.n == n
