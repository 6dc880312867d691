"""Paired comparisons: the statistics, `so101-sim compare` and `testing.assert_not_worse`."""

from __future__ import annotations

import json
import math
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
from eval_folders import write_eval_run

from so101_sim.cli import main
from so101_sim.harness import PolicyInfo, StepPolicy, evaluate
from so101_sim.harness.compare import compare_runs, seed_ranges
from so101_sim.harness.stats import (
    episodes_needed,
    episodes_needed_measured,
    mcnemar_p_value,
    paired_difference_interval,
    paired_episodes_needed,
    paired_power,
    paired_split,
)
from so101_sim.tasks import load_task
from so101_sim.testing import assert_not_worse
from so101_sim.utils.versions import cpu_description, setup_differences, software_versions


def test_mcnemar_matches_brute_force():
    def tail(k: int, m: int) -> float:
        return sum(math.comb(m, i) for i in range(k + 1)) / 2 ** m

    assert mcnemar_p_value(6, 16) == pytest.approx(2 * tail(6, 22), rel=1e-12)  # 0.0525
    assert mcnemar_p_value(6, 16, alternative="less") == pytest.approx(tail(6, 22), rel=1e-12)
    assert mcnemar_p_value(16, 6, alternative="less") == pytest.approx(tail(16, 22), rel=1e-12)
    assert mcnemar_p_value(0, 0) == 1.0 and mcnemar_p_value(5, 5) == 1.0
    assert mcnemar_p_value(0, 8, alternative="less") == pytest.approx(0.5 ** 8)
    with pytest.raises(ValueError, match="alternative"):
        mcnemar_p_value(1, 2, alternative="greater")


def test_newcombe_paired_interval_matches_published_value():
    # Cavo et al. (2012) as in Fagerland, Lydersen & Laake, "Statistical Analysis of
    # Contingency Tables", ch. 8: Newcombe square-and-add -0.0621 (-0.1186 to -0.0046).
    lo, hi = paired_difference_interval(59, 6, 16, 80)
    assert (lo, hi) == pytest.approx((-0.1186, -0.0046), abs=5e-5)
    lo, hi = paired_difference_interval(30, 0, 0, 20)  # identical runs: contains 0, symmetric
    assert lo < 0 < hi and lo == pytest.approx(-hi)
    assert paired_difference_interval(50, 0, 0, 0)[0] >= -1.0


def test_paired_split_keeps_only_the_shared_seeds_in_seed_order():
    a = {12: True, 3: True, 7: False, 5: False, 99: True}  # 99: a's alone
    b = {3: True, 12: False, 7: True, 5: False, 1: False}  # 1: b's alone
    assert paired_split(a, b) == ([3], [12], [7], [5])
    split = paired_split({s: s % 2 == 0 for s in range(20, 0, -1)},
                         {s: s % 3 == 0 for s in range(1, 21)})
    assert split.both == [6, 12, 18] and split.neither == [1, 5, 7, 11, 13, 17, 19]
    assert sum(map(len, split)) == 20 and paired_split({}, b) == ([], [], [], [])


def test_paired_needs_fewer_episodes_than_a_measured_baseline():
    # The README's table: drop 0.90 -> 0.80, alpha 0.01, power 0.8.
    assert episodes_needed(0.90, 0.80) == 122
    assert episodes_needed_measured(0.90, 0.80) == 389
    assert paired_episodes_needed(0.90, 0.80, discordant=0.10) == 90
    assert paired_episodes_needed(0.90, 0.80, discordant=0.20) == 208
    assert paired_episodes_needed(0.90, 0.80) == 272  # independent outcomes
    n = paired_episodes_needed(0.80, 0.60, discordant=0.2)
    assert paired_power(n, 0.80, 0.60, 0.2) >= 0.8 > paired_power(n - 1, 0.80, 0.60, 0.2)
    with pytest.raises(ValueError, match=r"discordant=0\.05"):
        paired_episodes_needed(0.9, 0.8, discordant=0.05)  # fewer disagreements than the drop


def _fake_run(root: Path, name: str, outcomes: dict[int, bool], task: str = "pick_place",
              sha: str = "t" * 64) -> Path:
    return write_eval_run(root / name, outcomes, task=task, sha=sha,
                          images=f"direct: rendered at 60x80 ({name})")


def test_compare_cli_writes_json_and_markdown(tmp_path, capsys):
    rng = np.random.default_rng(0)
    seeds = range(100_000, 100_040)
    a_ok = {s: bool(rng.random() < 0.8) for s in seeds}
    b_ok = {s: a_ok[s] and bool(rng.random() < 0.7) for s in seeds}  # B loses some of A's
    a = _fake_run(tmp_path, "cand", a_ok)
    b = _fake_run(tmp_path, "base", b_ok)
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "cmp")]) == 0
    out = capsys.readouterr().out
    r = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    p = r["paired"]
    assert p["only_b"] == 0 and p["only_a"] == sum(a_ok.values()) - sum(b_ok.values())
    assert sum(p.values()) == 40 and r["seeds"] == "100000..100039"
    assert r["mcnemar_p_two_sided"] == pytest.approx(mcnemar_p_value(p["only_a"], 0))
    lo, hi = r["difference_ci95_pp"]
    assert lo <= r["difference_pp"] <= hi
    md = (tmp_path / "cmp" / "compare.md").read_text()
    for text in ("McNemar", "Newcombe", "direct: rendered at 60x80 (cand)", "| **A failed** |"):
        assert text in md
    assert "A: cand" in out and "images: direct: rendered at 60x80 (base)" in out
    assert "exact McNemar p" in out and "Newcombe" in out


def test_the_images_line_stays_in_its_cell_of_the_comparison_table(tmp_path, capsys):
    """The default path's images line has "mean |diff| 0.26"; it split compare.md's rows."""
    import re

    runs = [_fake_run(tmp_path, name, {s: True for s in range(100_000, 100_004)})
            for name in ("cand", "base")]
    for run in runs:
        info = json.loads((run / "eval_info.json").read_text())
        info["config"]["images"] = "reduced: ...; mean |diff| 0.26, p99 5"
        (run / "eval_info.json").write_text(json.dumps(info))
    assert main(["compare", *map(str, runs), "--out", str(tmp_path / "cmp")]) == 0
    md = (tmp_path / "cmp" / "compare.md").read_text()
    rows = [x for x in md.splitlines() if x.startswith(("| A |", "| B |"))]
    assert len(rows) == 2
    for row in rows:  # run, policy, images, success, interval, folder
        assert len(re.split(r"(?<!\\)\|", row)) == 8, row
    assert "mean \\|diff\\| 0.26" in md


def test_one_seed_is_one_seed(tmp_path, capsys):
    """A one-episode smoke run was "paired on 1 seeds"; counts in user lines agree in number."""
    from so101_sim.utils.text import counted, seed_span

    a = _fake_run(tmp_path, "cand", {100_000: True})
    b = _fake_run(tmp_path, "base", {100_000: False})
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "cmp")]) == 0
    assert "paired on 1 seed of pick_place (100000)" in capsys.readouterr().out
    assert "the same 1 seed (100000)" in (tmp_path / "cmp" / "compare.md").read_text()
    assert [counted(n, "env") for n in (0, 1, 2)] == ["0 envs", "1 env", "2 envs"]
    assert counted(1, "paired episode") == "1 paired episode"
    assert counted(3, "copy", "copies") == "3 copies"
    assert seed_span(7, 7) == "seed 7" and seed_span(7, 9) == "seeds 7..9"


def test_compare_refuses_other_seeds_or_task(tmp_path, capsys):
    a = _fake_run(tmp_path, "a", dict.fromkeys(range(100_000, 100_010), True))
    b = _fake_run(tmp_path, "b", dict.fromkeys(range(100_000, 100_012), True))
    c = _fake_run(tmp_path, "c", dict.fromkeys(range(100_000, 100_010), True), task="stack")
    d = _fake_run(tmp_path, "d", dict.fromkeys(range(100_000, 100_010), True), sha="u" * 64)
    assert main(["compare", str(a), str(b)]) == 2
    err = capsys.readouterr().err
    assert "seeds: A has 10 (100000..100009), B has 12 (100000..100011)" in err
    assert "only in B: 100010..100011" in err and "--seed-start" in err
    with pytest.raises(ValueError, match="task: A ran 'pick_place', B ran 'stack'"):
        compare_runs(a, c)
    with pytest.raises(ValueError, match=r"task file: .* edited between the runs"):
        compare_runs(a, d)
    with pytest.raises(FileNotFoundError, match=r"no eval_info\.json: expected"):
        compare_runs(a, tmp_path)
    # a missing folder, a file, an interrupted eval: each named as what it is
    with pytest.raises(FileNotFoundError, match=r"nope does not exist: expected"):
        compare_runs(a, tmp_path / "nope")
    (tmp_path / "f.txt").write_text("x")
    with pytest.raises(FileNotFoundError, match=r"f\.txt is a file, not a folder"):
        compare_runs(a, tmp_path / "f.txt")
    (tmp_path / "cut").mkdir()
    (tmp_path / "cut" / "episodes.jsonl").write_text("")
    with pytest.raises(FileNotFoundError, match=r"interrupted; .* --out \S*cut --resume"):
        compare_runs(a, tmp_path / "cut")
    assert seed_ranges([5, 1, 2, 3, 9]) == "1..3, 5, 9"


def test_a_run_that_stopped_early_is_named_as_one(tmp_path, capsys):
    """`compare REF NEW` where NEW is an `eval --against REF` run that stopped after its
    verdict: refused (other seeds), and the error says that its verdict is the comparison."""
    ref = _fake_run(tmp_path, "ref", dict.fromkeys(range(100_000, 100_200), True))
    new = _fake_run(tmp_path, "new", dict.fromkeys(range(100_000, 100_060), False))
    info = json.loads((new / "eval_info.json").read_text())
    info["sequential_verdict"] = {"verdict": "worse", "episodes": 57, "against": str(ref)}
    (new / "eval_info.json").write_text(json.dumps(info))
    assert main(["compare", str(ref), str(new)]) == 2
    err = capsys.readouterr().err
    assert (f"B ({new}) is an `eval --against` run that stopped after 57 episodes with the "
            f"verdict 'worse': that verdict, in its eval_info.json (sequential_verdict), is its "
            f"comparison with {ref}") in err
    assert "A (" not in err
    assert "extend" not in err  # a stopped run is not extended: its test ended there


def test_a_run_on_the_first_seeds_of_the_other_is_told_how_to_extend(tmp_path, capsys):
    """100 seeds against 200 from the same start: `eval --resume --episodes 200` runs just the
    missing 100, so the error says so; seeds from another start get no such line."""
    big = _fake_run(tmp_path, "big", dict.fromkeys(range(100_000, 100_200), True))
    small = _fake_run(tmp_path, "small", dict.fromkeys(range(100_000, 100_100), True))
    assert main(["compare", str(big), str(small)]) == 2
    assert (f"; to pair all 200 seeds, extend B: run its eval command again with --out {small} "
            "--resume --episodes 200 (the 100 seeds already run are kept)"
            ) in capsys.readouterr().err
    shifted = _fake_run(tmp_path, "shifted", dict.fromkeys(range(100_050, 100_100), True))
    assert main(["compare", str(shifted), str(big)]) == 2
    assert "extend" not in capsys.readouterr().err


class _Rest:
    """Holds the rest pose: never grasps, so it fails every seed the expert solves."""

    def __init__(self) -> None:
        self.rest = np.asarray(load_task("pick_place").rest_pose, dtype=np.float32)

    def reset(self, seed: int) -> None:
        pass

    def select_action(self, obs: dict) -> np.ndarray:
        return self.rest


def test_assert_not_worse_on_the_baseline_seeds(tmp_path, capsys):
    base = tmp_path / "expert"
    evaluate("expert", episodes=8, n_envs=1, out_dir=base, videos=0, progress=False,
             report=False, log=lambda _: None)
    cfg = json.loads((base / "eval_info.json").read_text())["config"]
    assert cfg["software"] == software_versions() and cfg["cpu"] == cpu_description()
    assert cfg["software"]["mujoco"] == metadata.version("mujoco")
    check = assert_not_worse("expert", base, n_envs=1)  # the same policy: identical rollouts
    assert check.passed and check.p_value == 1.0
    assert check.comparison["identical_rollouts"] == 8
    assert check.comparison["setup_differences"] == []  # same machine, same software
    assert "one-sided exact McNemar p = 1" in capsys.readouterr().out

    rest = StepPolicy(_Rest, PolicyInfo(name="rest", fingerprint="rest"))
    with pytest.raises(pytest.fail.Exception, match="SIGNIFICANTLY WORSE"):
        assert_not_worse(rest, base, n_envs=1)  # 0/8 vs 8/8: p = 0.5**8 < 0.01


def test_compare_out_that_is_a_file_is_one_line(tmp_path, capsys):
    a = _fake_run(tmp_path, "a", dict.fromkeys(range(100_000, 100_004), True))
    b = _fake_run(tmp_path, "b", dict.fromkeys(range(100_000, 100_004), False))
    (tmp_path / "taken").write_text("a file, not a folder")
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "taken")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"so101-sim compare: error: compare --out {tmp_path / 'taken'} is a file; "
                   "expected a folder for compare.json and compare.md: choose another --out "
                   "(or leave it out)"]
    assert (tmp_path / "taken").read_text() == "a file, not a folder"


def test_comparing_a_folder_with_itself_warns(tmp_path, capsys):
    a = _fake_run(tmp_path, "a", dict.fromkeys(range(100_000, 100_004), True))
    assert main(["compare", str(a), str(a), "--out", str(tmp_path / "cmp")]) == 0
    warnings = [ln for ln in capsys.readouterr().out.splitlines() if "warning" in ln]
    assert warnings == [f"so101-sim compare: warning: A and B are the same folder ({a}); every "
                        "seed agrees with itself, so this says nothing about the policy: pass "
                        "two eval folders"]
    b = _fake_run(tmp_path, "b", dict.fromkeys(range(100_000, 100_004), True))
    compare_runs(a, b, log=lambda line: pytest.fail(f"warned about two folders: {line}"))


def test_a_missing_folder_compared_with_itself_gets_its_error_alone(tmp_path, capsys):
    missing = tmp_path / "not_run_yet"
    assert main(["compare", str(missing), str(missing)]) == 2
    out, err = capsys.readouterr()
    assert "warning" not in out + err
    assert err.strip().splitlines() == [
        f"so101-sim compare: error: {missing} does not exist: expected the --out folder of a "
        "finished `so101-sim eval`"]


def test_runs_on_other_software_or_cpu_are_compared_with_a_note(tmp_path, capsys):
    """Actions differ bitwise across torch releases and CPU instruction sets, so a paired
    comparison across them says so (files from before this was recorded: no note)."""
    seeds = range(100_000, 100_006)
    a = _fake_run(tmp_path, "a", dict.fromkeys(seeds, True))
    b = _fake_run(tmp_path, "b", dict.fromkeys(seeds, True))
    old = _fake_run(tmp_path, "old", dict.fromkeys(seeds, True))
    setup = {"software": software_versions(), "cpu": "Intel Xeon", "cpu_isa": "AVX512"}
    for run, torch_version, cpu, isa in ((a, "2.11.0", "Intel Xeon", "AVX512"),
                                         (b, "2.10.0", "AMD EPYC", "AVX2")):
        info = json.loads((run / "eval_info.json").read_text())
        info["config"].update(software={**setup["software"], "torch": torch_version}, cpu=cpu,
                              cpu_isa=isa)
        (run / "eval_info.json").write_text(json.dumps(info))
    assert setup_differences({}, setup) == []
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "cmp")]) == 0
    notes = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("note:")]
    assert notes == ["note: the runs differ in torch 2.11.0 vs 2.10.0; CPU Intel Xeon vs AMD "
                     "EPYC; torch's CPU kernels AVX512 vs AVX2: actions then differ bitwise and "
                     "some seeds' outcomes may differ for that reason alone, not the policy's"]
    assert "torch 2.11.0 vs 2.10.0" in (tmp_path / "cmp" / "compare.md").read_text()
    assert compare_runs(a, old, log=print)["setup_differences"] == []
    assert not [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("note:")]

    # b, resumed on a's setup after an earlier part on torch 2.10.0: that part still counts
    info = json.loads((b / "eval_info.json").read_text())
    earlier = {k: info["config"][k] for k in ("software", "cpu", "cpu_isa")}
    info["config"].update(software={**setup["software"], "torch": "2.11.0"}, cpu="Intel Xeon",
                          cpu_isa="AVX512", earlier_setups=[earlier])
    (b / "eval_info.json").write_text(json.dumps(info))
    assert compare_runs(a, b, log=print)["setup_differences"] == [
        "torch 2.11.0 vs 2.10.0", "CPU Intel Xeon vs AMD EPYC",
        "torch's CPU kernels AVX512 vs AVX2"]
    info["config"]["earlier_setups"] = []  # all on a's setup
    (b / "eval_info.json").write_text(json.dumps(info))
    assert compare_runs(a, b, log=print)["setup_differences"] == []
