"""``eval --against RUN``: RUN's seeds in order, stopped by the sequential paired test."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from so101_sim.harness import PolicyInfo, StepPolicy, evaluate
from so101_sim.harness.against import AgainstRun, evaluate_against
from so101_sim.harness.compare import RunSide

PICK_PLACE_TOML = Path(__file__).parents[1] / "envs" / "pick_place.toml"  # RUN's, as a path
REST = np.array([-10.374, -81.670, 77.846, 2.681, 123.209, 6.495], dtype=np.float32)


class _StandStill:
    def reset(self, seed: int) -> None:
        pass

    def select_action(self, obs: dict) -> np.ndarray:
        return REST


def _stand_still() -> StepPolicy:
    return StepPolicy(_StandStill, PolicyInfo(name="stand_still", fingerprint="rest"))


def _side(outcomes: dict[int, bool]) -> RunSide:
    return RunSide(path=Path("ref"), policy="ref", fingerprint="f", task="pick_place",
                   task_sha256=None, images="", success=outcomes,
                   actions_sha=dict.fromkeys(outcomes))


@pytest.fixture(scope="module")
def expert_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("against") / "expert"
    evaluate("expert", episodes=60, n_envs=2, out_dir=out, videos=0, progress=False,
             report=False, log=lambda _: None)
    return out


def test_pairs_enter_the_test_in_seed_order_only():
    stop = AgainstRun(_side(dict.fromkeys(range(100, 110), True)))
    done = {102: SimpleNamespace(success=False), 101: SimpleNamespace(success=False)}
    assert not stop.update(done) and stop.test.episodes == 0  # seed 100 is not back yet
    done[100] = SimpleNamespace(success=False)
    stop.update(done)
    assert stop.test.episodes == 3
    assert stop.verdict().statistic["losses"] == 3


def test_refuses_a_run_with_gaps():
    with pytest.raises(ValueError, match="not consecutive"):
        AgainstRun(_side({100: True, 102: True}))


def test_a_broken_policy_is_declared_worse_early(expert_run, tmp_path):
    out = tmp_path / "broken"
    result = evaluate_against(_stand_still(), expert_run, n_envs=2, out_dir=out, videos=0,
                              progress=False, report=False, log=lambda _: None)
    verdict = result["sequential_verdict"]
    assert verdict["verdict"] == "worse"
    assert verdict["episodes"] < 20  # of the 60 seeds: it stopped once it knew
    assert result["aggregated"]["n_episodes"] < 60
    saved = json.loads((out / "eval_info.json").read_text())
    assert saved["sequential_verdict"]["verdict"] == "worse"
    # a stopped run with a gap (an episode past the prefix came back) as the next reference:
    # the refusal says what it is and names the full run it was measured against
    gapped = dataclasses.replace(_side({100000: True, 100002: True}), path=out)
    with pytest.raises(ValueError, match=r"not consecutive .* it is an `eval --against` run, "
                                         r"stopped once its test decided.*"
                                         + re.escape(f"({expert_run})")):
        AgainstRun(gapped)


def test_a_resumed_run_that_its_episodes_decide_runs_no_more(expert_run, tmp_path):
    out = tmp_path / "broken"
    first = evaluate_against(_stand_still(), expert_run, n_envs=2, out_dir=out, videos=0,
                             progress=False, report=False, log=lambda _: None)
    again = evaluate_against(_stand_still(), expert_run, n_envs=2, out_dir=out, videos=0,
                             progress=False, report=False, resume=True, log=lambda _: None)
    assert again["sequential_verdict"]["verdict"] == "worse"
    assert again["sequential_verdict"]["episodes"] == first["sequential_verdict"]["episodes"]
    assert again["aggregated"]["n_episodes"] == first["aggregated"]["n_episodes"]


def test_out_that_is_the_against_run_itself_is_refused(expert_run, tmp_path, capsys):
    from so101_sim.cli import main

    ref = tmp_path / "ref"
    shutil.copytree(expert_run, ref)
    before = {p.name: p.read_bytes() for p in ref.iterdir() if p.is_file()}
    for resume in ([], ["--resume"]):
        assert main(["eval", "--policy", "expert", "--against", str(ref), "--out",
                     str(ref / "."), *resume]) == 2
        assert capsys.readouterr().err.strip().splitlines() == [
            f"so101-sim eval: error: --out {ref / '.'} is the --against run itself: its "
            "episodes and verdict would be written into the reference they are tested "
            "against; choose another --out (or leave it out)"]
    with pytest.raises(ValueError, match="is the --against run itself"):
        evaluate_against(_stand_still(), ref, out_dir=ref, log=lambda _: None)
    assert {p.name: p.read_bytes() for p in ref.iterdir() if p.is_file()} == before


def test_the_expert_against_itself_is_not_worse(expert_run, tmp_path, capsys):
    from so101_sim.cli import main

    out = tmp_path / "same"
    assert main(["eval", "--policy", "expert", "--against", str(expert_run), "--n-envs", "2",
                 "--videos", "0", "--out", str(out), "--task", str(PICK_PLACE_TOML)]) == 0
    verdict = json.loads((out / "eval_info.json").read_text())["sequential_verdict"]
    assert verdict["verdict"] == "not worse" and verdict["episodes"] <= 60
    out_text = capsys.readouterr().out
    assert "sequential verdict: not worse" in out_text and "note:" not in out_text


def test_another_task_is_refused_before_anything_runs(expert_run, tmp_path):
    with pytest.raises(ValueError, match=r"--task lift given with --against .*'pick_place'"):
        evaluate_against("expert", expert_run, task="lift", out_dir=tmp_path / "lift")
    assert not (tmp_path / "lift").exists()


def test_max_episodes_gives_undecided(expert_run, tmp_path):
    """... and a reference measured on another CPU is paired with a note saying so."""
    other = tmp_path / "other_cpu"
    shutil.copytree(expert_run, other)
    info = json.loads((other / "eval_info.json").read_text())
    info["config"]["cpu"] = "Some Other CPU"
    (other / "eval_info.json").write_text(json.dumps(info))
    lines: list[str] = []
    result = evaluate_against("expert", other, max_episodes=5, n_envs=2,
                              out_dir=tmp_path / "short", videos=0, progress=False,
                              report=False, log=lines.append)
    assert result["sequential_verdict"]["verdict"] == "undecided"
    assert result["sequential_verdict"]["episodes"] == 5
    assert not any("without a decision" in line for line in lines)  # --max-episodes stopped it
    assert lines[-1] == (f"so101-sim eval: note: the runs differ in CPU Some Other CPU vs "
                         f"{result['config']['cpu']}: actions then differ bitwise and some "
                         "seeds' outcomes may differ for that reason alone, not the policy's")


def test_running_out_of_the_runs_seeds_says_how_to_go_on(tmp_path, capsys):
    """... and the commands it gives extend RUN and resume the --against run onto its new
    seeds, the episodes already run kept."""
    from so101_sim.cli import main

    short, again = tmp_path / "short_ref", tmp_path / "again"
    evaluate("expert", episodes=4, n_envs=2, out_dir=short, videos=0, progress=False,
             report=False, log=lambda _: None)
    argv = ["eval", "--policy", "expert", "--against", str(short), "--n-envs", "2",
            "--videos", "0", "--out", str(again)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert json.loads((again / "eval_info.json").read_text())["sequential_verdict"][
        "verdict"] == "undecided"
    hint = (f"so101-sim eval: all 4 seeds of {short} ran without a decision; to go on, extend "
            f"it: run its eval command again with --out {short} --resume --episodes 8 (the 4 "
            f"seeds already run are kept), then so101-sim {' '.join(argv)} --resume (its 4 "
            "episodes are kept too)")
    assert hint in out.splitlines()
    assert main(["eval", "--policy", "expert", "--out", str(short), "--resume", "--episodes",
                 "8", "--n-envs", "2", "--videos", "0"]) == 0
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 0
    out = capsys.readouterr().out
    assert "(4 done, 4 to run)" in out and "undecided after 8 paired episodes" in out


@pytest.mark.parametrize(("flags", "message"), [
    (["--task", "lift"], "--task lift given with --against .* measured on 'pick_place'"),
    (["--task", "pick_place,lift"], "--task pick_place,lift given with --against"),
    (["--episodes", "20"], "--episodes 20 given with --against: the seeds come from"),
    (["--seed-start", "100010"], "--seed-start 100010 given with --against"),
])
def test_flags_the_run_decides_are_refused_beside_against(expert_run, tmp_path, capsys,
                                                          flags, message):
    """RUN decides the task and seeds; a flag that would be silently overridden is an error
    naming it, before anything loads or runs."""
    from so101_sim.cli import main

    out = tmp_path / "refused"
    assert main(["eval", "--policy", "expert", "--against", str(expert_run), "--out", str(out),
                 *flags]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and "drop" in err
    assert not out.exists()


@pytest.mark.parametrize("flags", [["--margin", "0.05"], ["--alpha", "0.01"],
                                   ["--indifference", "0.2"], ["--max-episodes", "30"]])
def test_sequential_flags_without_against_are_refused(tmp_path, capsys, flags):
    from so101_sim.cli import main

    out = tmp_path / "refused"
    assert main(["eval", "--policy", "expert", "--episodes", "2", "--out", str(out),
                 *flags]) == 2
    err = capsys.readouterr().err
    assert f"{flags[0]} given without --against" in err and not out.exists()


@pytest.mark.parametrize(("flags", "message"), [
    (["--margin", "5"], "margin must be a fraction in [0, 1) (5 points = 0.05), got 5.0"),
    (["--alpha", "0"], "alpha must be an error rate in (0, 0.5), got 0.0"),
    (["--indifference", "0"], "indifference must be a fraction > 0"),
])
def test_bad_sequential_flags_are_named_before_the_policy_loads(expert_run, tmp_path, capsys,
                                                                monkeypatch, flags, message):
    """A checkpoint takes seconds to load; a --margin in points instead of a fraction is
    refused first, in one line."""
    import so101_sim.harness
    from so101_sim.cli import main

    def no_load(*args, **kwargs):
        raise AssertionError("the policy was loaded before the flags were checked")

    monkeypatch.setattr(so101_sim.harness, "load_policy", no_load)
    out = tmp_path / "refused"
    assert main(["eval", "--policy", "expert", "--against", str(expert_run), "--out", str(out),
                 *flags]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_run_rendered_at_another_size_gets_a_note(tmp_path):
    """A policy that sees frames can part on small frame differences alone, so --against a RUN
    rendered at another size says so and names the flag that renders as RUN did; a RUN of the
    same size gets none."""
    info = PolicyInfo(name="stand_still_eyes", cameras=("front", "side"), image_size=(48, 64),
                      fingerprint="rest-eyes")
    policy = StepPolicy(_StandStill, info)
    quiet = dict(n_envs=2, videos=0, progress=False, report=False, log=lambda _: None)
    ref = tmp_path / "ref"
    evaluate(policy, episodes=2, out_dir=ref, image_size=(96, 128), **quiet)
    lines: list[str] = []
    result = evaluate_against(policy, ref, max_episodes=2, out_dir=tmp_path / "new",
                              **{**quiet, "log": lines.append})
    assert result["config"]["render_size"] == [48, 64]  # the policy's input size, no resize
    assert lines[-1] == (f"so101-sim eval: note: {ref} rendered the cameras at 96x128, this run "
                         "at 48x64: frames differ slightly, and some seeds' outcomes may differ "
                         "for that reason alone, not the policy's; --image-size 96x128 renders "
                         "as it did")
    lines.clear()
    evaluate_against(policy, ref, max_episodes=2, out_dir=tmp_path / "same", image_size=(96, 128),
                     **{**quiet, "log": lines.append})
    assert not any("rendered the cameras" in line for line in lines)


def test_a_state_only_policy_gets_no_render_note(expert_run, tmp_path):
    """The expert sees no frames, so its runs' render sizes (the videos') touch no outcome."""
    lines: list[str] = []
    result = evaluate_against("expert", expert_run, max_episodes=2, n_envs=2, videos=1,
                              image_size=(96, 128), out_dir=tmp_path / "x", progress=False,
                              report=False, log=lines.append)
    theirs = json.loads((expert_run / "eval_info.json").read_text())["config"]["render_size"]
    assert result["config"]["render_size"] == [96, 128] != theirs  # the videos' sizes differ
    assert not any("rendered the cameras" in line for line in lines)
