"""`so101-sim compare` of two `eval --task a,b` folders: task by task, then pooled.

Before, a suite folder was taken for lerobot-eval's result ("keeps no seed per episode").
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from so101_sim.cli import main
from so101_sim.harness.compare import load_run
from so101_sim.harness.stats import mcnemar_p_value
from so101_sim.harness.suite import SUITE_INFO, suite_info

SEEDS = range(100_000, 100_030)


def suite(root: Path, name: str, outcomes: dict[str, dict[int, bool]]) -> Path:
    """A suite folder as `eval --task a,b` writes it: one eval folder per task, and the
    grouped eval_info.json from the harness's own `suite_info`."""
    out = root / name
    results = {}
    for task, ok in outcomes.items():
        episodes = [{"seed": s, "success": v, "sum_reward": float(v), "max_reward": float(v),
                     "actions_sha": f"{name}{task}{s}"} for s, v in ok.items()]
        config = {"policy": name, "policy_fingerprint": name[:4], "task": task,
                  "task_sha256": "t" * 64, "images": "no camera input (state only)",
                  "seed_start": min(ok), "episodes": len(ok)}
        k = sum(ok.values())
        results[task] = {"per_episode": episodes, "config": config,
                         "aggregated": {"n_episodes": len(ok), "n_success": k,
                                        "pc_success": 100.0 * k / len(ok)}}
        (out / task).mkdir(parents=True)
        (out / task / "eval_config.json").write_text(json.dumps(config))  # as RunDir.prepare
        (out / task / "eval_info.json").write_text(json.dumps(
            {"per_episode": episodes, "config": config, "aggregated": results[task]["aggregated"]}))
    (out / SUITE_INFO).write_text(json.dumps(suite_info(results, 1.0, out, name)))
    return out


@pytest.fixture
def two_suites(tmp_path: Path) -> tuple[Path, Path, dict, dict]:
    rng = np.random.default_rng(1)
    a_ok = {t: {s: bool(rng.random() < 0.9) for s in SEEDS} for t in ("lift", "stack")}
    b_ok = {t: {s: a_ok[t][s] and bool(rng.random() < 0.7) for s in SEEDS} for t in a_ok}
    return suite(tmp_path, "new", a_ok), suite(tmp_path, "old", b_ok), a_ok, b_ok


def test_two_suites_are_compared_task_by_task_and_pooled(tmp_path, two_suites, capsys):
    a, b, a_ok, b_ok = two_suites
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "cmp")]) == 0
    out = capsys.readouterr().out
    r = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert r["tasks"] == ["lift", "stack"]
    lost = {t: sum(a_ok[t].values()) - sum(b_ok[t].values()) for t in a_ok}
    for task in a_ok:  # each task is the ordinary pair, filed under its own name
        assert r["per_task"][task]["paired"]["only_a"] == lost[task] > 0
        assert r["per_task"][task]["paired"]["only_b"] == 0
        assert (tmp_path / "cmp" / task / "compare.md").is_file()
    pooled = r["pooled"]
    assert pooled["n_pairs"] == 2 * len(SEEDS)
    assert pooled["paired"]["only_a"] == sum(lost.values())
    assert pooled["mcnemar_p_two_sided"] == pytest.approx(mcnemar_p_value(sum(lost.values()), 0))
    assert pooled["difference_pp"] == pytest.approx(100 * sum(lost.values()) / 60)
    rows = [ln for ln in out.splitlines() if ln.startswith("| ")]
    assert [ln.split(" | ")[0] for ln in rows[2:]] == ["| lift", "| stack", "| all, pooled"]
    assert "pooled over 2 tasks: A is significantly better at 0.05" in out
    assert "all, pooled" in (tmp_path / "cmp" / "compare.md").read_text()


def test_a_suite_against_one_task_names_the_pair_that_works(tmp_path, two_suites, capsys):
    a = two_suites[0]
    single = a / "stack"
    assert main(["compare", str(single), str(a)]) == 2
    err = capsys.readouterr().err
    assert f"so101-sim compare {single} {a / 'stack'}" in err
    assert "lerobot-eval" not in err
    with pytest.raises(ValueError, match=r"eval --task a,b` folder"):
        load_run(a)
    assert main(["eval", "--policy", "expert", "--against", str(a),
                 "--out", str(tmp_path / "e")]) == 2
    assert f"give one task's subfolder, e.g. {a / 'lift'}" in capsys.readouterr().err


def test_suites_with_other_tasks_compare_the_shared_ones(tmp_path, capsys):
    ok = dict.fromkeys(SEEDS, True)
    a = suite(tmp_path, "a", {"lift": ok, "stack": ok})
    b = suite(tmp_path, "b", {"stack": ok, "tidy": ok})
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "cmp")]) == 0
    out = capsys.readouterr().out
    assert "comparing the 1 task both ran; only in A: lift, only in B: tidy" in out
    assert json.loads((tmp_path / "cmp" / "compare.json").read_text())["tasks"] == ["stack"]
    c = suite(tmp_path, "c", {"tidy": ok})
    assert main(["compare", str(a), str(c)]) == 2
    assert "share no task" in capsys.readouterr().err


def test_a_suite_against_itself_warns_once(tmp_path, two_suites, capsys):
    a = two_suites[0]
    assert main(["compare", str(a), str(a), "--out", str(tmp_path / "cmp")]) == 0
    warnings = [ln for ln in capsys.readouterr().out.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and f"same folder ({a})" in warnings[0]


def test_an_interrupted_suite_is_named_as_one(tmp_path, two_suites, capsys):
    """A suite killed before its last task has per-task folders and no eval_info.json of its
    own: it was taken for one task's run ("compare that task's subfolder")."""
    a = two_suites[0]
    (a / SUITE_INFO).unlink()
    (a / "stack" / "eval_info.json").unlink()
    (a / "stack" / "episodes.jsonl").write_text("")
    assert main(["compare", str(a), str(two_suites[1])]) == 2
    err = capsys.readouterr().err
    assert (f"{a} has no eval_info.json yet: it holds the tasks stack of an interrupted `eval "
            f"--task a,b`; finish it by running its command again with --out {a} --resume") in err


def test_a_folder_of_runs_names_them_not_an_interrupted_suite(tmp_path, two_suites, capsys):
    """`compare outputs/eval ...`, the folder every default --out goes under, was called "the
    tasks ... of an interrupted `eval --task a,b`" and told to --resume."""
    runs = tmp_path / "outputs" / "eval"
    for age, name in enumerate(("expert-pick_place-20261205-104526",
                                "expert-pick_place-20261205-104525")):
        shutil.copytree(two_suites[0] / "stack", runs / name)
        (runs / name / "episodes.jsonl").write_text("")
        os.utime(runs / name / "episodes.jsonl", (1e9 - age, 1e9 - age))  # the first, latest
    assert main(["compare", str(runs), str(two_suites[1] / "stack")]) == 2
    err = capsys.readouterr().err
    assert (f"{runs} has no eval_info.json: it is a folder of 2 eval runs "
            "(expert-pick_place-20261205-104525, expert-pick_place-20261205-104526); pass one "
            f"of them, e.g. {runs / 'expert-pick_place-20261205-104526'}") in err
    assert "interrupted" not in err and "--resume" not in err
