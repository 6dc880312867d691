"""``--policy baseline``: policy/baselines.toml answers for every task of the suite, a shipped
entry resolves to weights, and a task without weights gets one line naming its card and recipe
(checked on a table of our own, since every task of the repo's table may have weights)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import so101_sim.harness.baselines as baselines_module
from so101_sim.cli import main
from so101_sim.harness.baselines import baseline_checkpoint, baselines
from so101_sim.tasks import available_tasks, load_task
from so101_sim.utils.paths import data_dir, policy_dir

REPO = data_dir("policy").parent


def test_every_task_has_an_entry_with_a_card_and_a_recipe() -> None:
    table = baselines()
    assert sorted(table) == available_tasks()
    for task, entry in table.items():
        assert (REPO / entry["card"]).is_file(), f"{task}: card {entry['card']} is missing"
        assert entry["recipe"], task
        if "checkpoint" in entry:
            folder = baseline_checkpoint(load_task(task))
            assert folder == policy_dir() / entry["checkpoint"]
            assert (folder / "model.safetensors").is_file()


@pytest.fixture
def own_table(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A policy/ folder whose table ships pick_place only (the repo's weights, copied)."""
    root = tmp_path / "policy"
    shutil.copytree(policy_dir() / "pick_place_diffusion", root / "pick_place_diffusion")
    (root / "baselines.toml").write_text(
        '[pick_place]\ncheckpoint = "pick_place_diffusion"\ncard = "c/pp.md"\nrecipe = "r1"\n\n'
        '[tidy]\ncard = "c/tidy.md"\nrecipe = "README.md, Baselines: train tidy"\n')
    monkeypatch.setattr(baselines_module, "policy_dir", lambda: root)
    return root


def test_a_task_without_weights_gets_one_line_naming_card_and_recipe(own_table: Path,
                                                                    capsys) -> None:
    with pytest.raises(ValueError, match=r"no weights are shipped for 'tidy'; its card: "
                                         r"c/tidy\.md; train it yourself: README\.md, "
                                         r"Baselines: train tidy"):
        baseline_checkpoint(load_task("tidy"))
    with pytest.raises(ValueError, match=r"'lift' has no baseline entry; tasks with one: "
                                         r"\['pick_place', 'tidy'\]"):
        baseline_checkpoint(load_task("lift"))
    assert main(["eval", "--policy", "baseline", "--task", "tidy", "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "c/tidy.md" in err and "train tidy" in err


def test_baseline_on_several_tasks_runs_the_shipped_ones_and_names_the_rest(
        own_table: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "suite"
    assert main(["eval", "--policy", "baseline", "--task", "pick_place,tidy", "--episodes", "1",
                 "--n-envs", "1", "--videos", "0", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "no shipped weights for ['tidy']" in said
    assert (out / "pick_place" / "eval_info.json").is_file() and not (out / "tidy").exists()
