"""eval's and curve's default task is the one the checkpoint's demos were of; a task the demos
never showed gets one line. The sidecar is what `train` writes (tests/test_training.py checks
that it writes these keys)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from so101_sim.cli.commands import cmd_curve, resolve_eval_flags
from so101_sim.cli.parser import build_parser
from so101_sim.harness.trained_on import default_task, unseen_task_note
from so101_sim.tasks import load_task
from so101_sim.train.checkpoint import TRAIN_INFO

STACK = load_task("stack").description


def checkpoint(root: Path, **info: object) -> Path:
    root.mkdir(parents=True)
    (root / TRAIN_INFO).write_text(json.dumps({"step": 2, **info}))
    return root


def eval_args(*argv: str):
    return build_parser().parse_args(["eval", *argv])


def test_eval_defaults_to_the_task_of_the_demos(tmp_path: Path, capsys) -> None:
    ck = checkpoint(tmp_path / "ck", dataset_task="stack", dataset_task_texts=[STACK])
    args = eval_args("--policy", str(ck))
    resolve_eval_flags(args)
    assert args.task == "stack"
    assert f"task: stack, the task of the demos {ck} was trained on" in capsys.readouterr().out
    chosen = eval_args("--policy", str(ck), "--task", "lift")
    resolve_eval_flags(chosen)
    assert chosen.task == "lift" and capsys.readouterr().out == ""


def test_a_checkpoint_without_the_keys_keeps_pick_place(tmp_path: Path, capsys) -> None:
    for policy in (str(checkpoint(tmp_path / "old", preset="cpu")), "expert",
                   str(tmp_path / "missing")):
        args = eval_args("--policy", policy)
        resolve_eval_flags(args)
        assert args.task == "pick_place"
    assert capsys.readouterr().out == ""
    assert unseen_task_note(tmp_path / "old", ["stack"]) is None


def test_a_task_file_that_is_not_here_falls_back_with_a_note(tmp_path: Path, capsys) -> None:
    ck = checkpoint(tmp_path / "ck", dataset_task="/elsewhere/my_task.toml")
    assert default_task(str(ck), "pick_place") == "pick_place"
    out = capsys.readouterr().out
    assert "'/elsewhere/my_task.toml', which does not load here" in out
    assert "using the default task" in out


def test_a_task_the_demos_never_showed_gets_one_line(tmp_path: Path) -> None:
    ck = checkpoint(tmp_path / "ck", dataset_task="stack", dataset_task_texts=[STACK])
    assert unseen_task_note(ck, ["stack"]) is None
    note = unseen_task_note(ck, ["pick_place"])
    assert note.startswith(f"note: pick_place ({load_task('pick_place').description!r}) is "
                           f"not a task {ck} was trained on (its demos: {STACK!r})")
    # the pick_place variants share pick_place's text: the same instruction, no note
    pp = checkpoint(tmp_path / "pp", dataset_task="pick_place",
                    dataset_task_texts=[load_task("pick_place").description])
    assert unseen_task_note(pp, ["pick_place_dr", "pick_place_anywhere"]) is None
    # several tasks (eval --task a,b): one line naming those the demos never showed
    note = unseen_task_note(pp, ["lift", "pick_place", "stack"])
    assert note.startswith(f"note: lift, stack are not tasks {pp} was trained on (its demos: ")


def test_the_shipped_policy_says_it_learned_pick_place() -> None:
    """Its sidecar predated these keys, so `eval --task lift` of it said nothing before
    scoring about 0. It was trained on `record` of the default task, training seeds 0..199
    (README's recipe)."""
    shipped = Path(__file__).parents[1] / "policy" / "pick_place_diffusion"
    assert default_task(str(shipped), "lift") == "pick_place"
    assert unseen_task_note(shipped, ["pick_place"]) is None
    note = unseen_task_note(shipped, ["lift"])
    assert note is not None and "expect a low rate" in note


def test_curve_defaults_to_the_task_of_the_run(tmp_path: Path, monkeypatch, capsys) -> None:
    run = tmp_path / "run"
    for step in (2, 4):
        ck = checkpoint(run / "checkpoints" / f"step_{step:07d}" / "pretrained_model",
                        dataset_task="lift")
        (ck / "model.safetensors").write_bytes(b"")
    seen = {}

    def fake_curve(run, **kw):
        seen["task"] = kw["task"]
        raise SystemExit(0)

    import so101_sim.harness.curve as curve

    monkeypatch.setattr(curve, "evaluate_curve", fake_curve)
    with pytest.raises(SystemExit):
        cmd_curve(build_parser().parse_args(["curve", str(run)]))
    assert seen["task"] == "lift" and "task: lift, the task of the demos" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cmd_curve(build_parser().parse_args(["curve", str(run), "--task", "stack"]))
    assert seen["task"] == "stack"


def test_an_unmeasured_card_names_the_task_of_the_demos() -> None:
    from so101_sim.harness.export import model_card

    shipped = Path(__file__).parent.parent / "policy" / "pick_place_diffusion" / TRAIN_INFO
    info = json.loads(shipped.read_text())
    assert model_card(info, None, [], "cpu").startswith(
        "# pick_place_diffusion: Diffusion Policy for so101_sim/PickPlace-v0, task pick_place\n")
    card = model_card({**info, "dataset_task": "lift"}, None, [], "cpu", name="lift_run")
    assert card.startswith("# lift_run: Diffusion Policy for so101_sim/PickPlace-v0, task lift\n")
    assert "evaluation seeds in the data" not in card
    card = model_card({**info, "dataset_eval_seeds": [[100000, 100049]]}, None, [], "cpu")
    assert ("| evaluation seeds in the data | 100000..100049 (rollouts; eval and export refuse "
            "to measure it on them) |") in card


def test_train_records_the_evaluation_seeds_among_its_demos(tmp_path: Path) -> None:
    from so101_sim.train.checkpoint import demos_info, eval_seeds_note

    info = demos_info("lift", ["b", "a"],
                      [3, 100003, 0, 100000, 100001, 100009, 100010, 100012])
    assert info == {"dataset_task": "lift", "dataset_task_texts": ["a", "b"],
                    "dataset_eval_seeds": [[100000, 100001], [100003, 100003],
                                           [100009, 100010], [100012, 100012]]}
    assert eval_seeds_note(tmp_path, info) == (
        f"so101-sim train: note: {tmp_path} holds episodes on evaluation seeds (100000..100001, "
        "100003, 100009..100010, 100012), e.g. rollouts of `eval --save-rollouts`; eval will "
        "refuse to measure this policy on them (its own training episodes): evaluate it with "
        "--seed-start above 100012")
    recorded = demos_info(None, [], list(range(50)))  # record's demos: training seeds only
    assert recorded["dataset_eval_seeds"] == [] and eval_seeds_note(tmp_path, recorded) is None
    assert demos_info(None, [], None)["dataset_eval_seeds"] == []  # a dataset without seeds
    # no sidecar (e.g. after lerobot-edit-dataset): a text only one task has names it
    lift = load_task("lift").description
    assert demos_info(None, [lift], None)["dataset_task"] == "lift"
    assert demos_info(None, [load_task("pick_place").description], None)["dataset_task"] is None
    assert demos_info(None, [lift, STACK], None)["dataset_task"] is None  # a merge of several


def test_eval_refuses_the_seeds_of_its_own_training_rollouts() -> None:
    from so101_sim.harness.trained_on import check_unseen_seeds

    lift, stack = load_task("lift"), load_task("stack")
    demos = {"dataset_task": "lift", "dataset_eval_seeds": [[100000, 100049]]}
    with pytest.raises(ValueError, match=r"seeds 100040\.\.100049 of lift are among the "
                                         r"policy's training episodes .*--seed-start 100050\)"):
        check_unseen_seeds(demos, lift, range(100040, 100090), False)
    check_unseen_seeds(demos, lift, range(100050, 100090), False)  # later seeds: fine
    check_unseen_seeds(demos, lift, range(100000, 100010), True)  # --allow-train-seeds
    check_unseen_seeds(demos, stack, range(100000, 100010), False)  # another task's scenes
    merged = {"dataset_task": None, "dataset_eval_seeds": [[100000, 100000]]}  # task unknown
    with pytest.raises(ValueError, match="seed 100000 of stack is among"):
        check_unseen_seeds(merged, stack, range(100000, 100010), False)
    with pytest.raises(ValueError, match=r"dataset_eval_seeds=\[100000\] .* is invalid"):
        check_unseen_seeds({"dataset_eval_seeds": [100000]}, stack, range(100000, 100001), False)
    check_unseen_seeds({}, stack, range(100000, 100001), False)  # a checkpoint that does not say


def test_export_refuses_an_eval_on_the_policys_own_rollout_seeds(tmp_path: Path) -> None:
    from so101_sim.harness.export import check_measured

    ck = checkpoint(tmp_path / "ck", dataset_task="lift", dataset_eval_seeds=[[100000, 100009]])

    def measured(task: str, *seeds: int) -> list:
        e = {"config": {"policy_weights": "w", "policy": "ck", "task": task},
             "per_episode": [{"seed": s} for s in seeds]}
        return [(tmp_path / "eval_info.json", e)]

    with pytest.raises(ValueError, match=r"eval_info.json cannot go into the card: seeds "
                                         r"100008\.\.100009 of lift are among"):
        check_measured(measured("lift", 100008, 100009, 100010), "w", ck, log=print)
    check_measured(measured("lift", 100010, 100011), "w", ck, log=print)  # held out
    check_measured(measured("stack", 100000), "w", ck, log=print)  # another task's scenes


def test_a_suite_refuses_before_its_first_task_runs(tmp_path: Path) -> None:
    """Only a sidecar, no weights: pick_place, first in the list, would fail to load; the
    refusal for lift comes before anything is loaded or run."""
    from so101_sim.harness.suite import evaluate_suite

    ck = checkpoint(tmp_path / "ck", dataset_task="lift", dataset_eval_seeds=[[100000, 100001]])
    with pytest.raises(ValueError, match=r"seeds 100000\.\.100001 of lift are among"):
        evaluate_suite(str(ck), ["pick_place", "lift"], out_dir=tmp_path / "out", episodes=4,
                       log=print)
    with pytest.raises(FileNotFoundError, match=r"has no config\.json"):  # later seeds: it runs
        evaluate_suite(str(ck), ["pick_place", "lift"], out_dir=tmp_path / "out", episodes=4,
                       seed_start=100002, log=print)
    assert not (tmp_path / "out").exists()


def test_the_failures_note_quotes_its_paths() -> None:
    from so101_sim.train.demos import failures_note

    assert failures_note(Path("ds"), "local/x", [], 5) is None
    note = failures_note(Path("my data/ro"), "local/x", [0, 3], 5)
    assert note.endswith("--root 'my data/ro' --new_repo_id local/x_ok --new_root "
                         "'my data/ro_ok' --operation.type delete_episodes "
                         "--operation.episode_indices '[0, 3]'")
    assert "2 of 5 episodes in my data/ro failed" in note
