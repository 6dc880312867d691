"""lerobot's flags given to `so101-sim` are answered with this CLI's command line."""

from __future__ import annotations

import shlex

import pytest

from so101_sim.cli.lerobot_flags import LEROBOT_FLAGS
from so101_sim.cli.parser import build_parsers, parse_command_line


def test_every_mapped_flag_is_a_flag_of_its_command() -> None:
    """A renamed flag would otherwise leave the hint naming a flag that fails in turn."""
    _, commands = build_parsers()
    for name, mapping in LEROBOT_FLAGS.items():
        flags = {s for a in commands[name]._actions for s in a.option_strings}
        assert {new for new in mapping.values() if new} <= flags, name
        if "" in mapping.values():  # the value alone: the command takes a positional
            assert any(not a.option_strings for a in commands[name]._actions
                       if a.dest != "help"), name
        assert not set(mapping) & flags, name  # a mapped spelling must not be a real flag


@pytest.mark.parametrize(("argv", "meant"), [
    ("eval --policy.path=policy/p --eval.n_episodes=10 --eval.batch_size=2",
     "eval --policy policy/p --episodes 10 --n-envs 2"),
    ("eval --env.type=so101_pick_place --env.task=lift --policy.path policy/p --output_dir=o",
     "eval --task lift --policy policy/p --out o"),
    ("eval --policy p --env.type so101_pick_place --eval.use_async_envs=true --out o",
     "eval --policy p --out o"),
    ("eval --policy p --policy.n_action_steps=4 --workers 2 --out o",
     "eval --policy p --n-action-steps 4 --n-envs 2 --out o"),
    ("curve r --eval.n_episodes=8", "curve r --episodes 8"),
    ("train --dataset.repo_id=local/d --dataset.root=data/d --policy.type=diffusion "
     "--output_dir=r --batch_size=32", "train --dataset data/d --preset cpu --out r "
                                       "--batch-size 32"),
    ("train --dataset.root=d --policy.type act --out r", "train --dataset d --preset act --out r"),
    ("train --dataset d --policy.path=runs/a/pretrained_model --out r",
     "train --dataset d --init-from runs/a/pretrained_model --out r"),
    ("record --dataset.root=d --dataset.num_episodes=5 --n-envs 2",
     "record --out d --episodes 5 --workers 2"),
    ("explain --dataset.root=d --policy.path=p", "explain --dataset d --policy p"),
    ("replay --robot.type=so101_sim --dataset.repo_id=local/d --dataset.root=data/d "
     "--dataset.episode=1", "replay data/d --episode 1"),
    ("export --policy.path=runs/a/pretrained_model --out policy/p",
     "export runs/a/pretrained_model --out policy/p"),
])
def test_lerobot_flags_get_the_command_line_that_parses(argv: str, meant: str, capsys) -> None:
    """`eval --policy.path=P` was answered "did you mean --policy-batch?"; now with the whole
    command line in so101-sim's flags, and that line parses."""
    with pytest.raises(SystemExit) as exc:
        parse_command_line(shlex.split(argv))
    assert exc.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    name = argv.split()[0]
    assert last.startswith(f"so101-sim {name}: error: unrecognized arguments: ")
    assert last.endswith(f"; so101-sim {name} spells them: so101-sim {meant}")
    args = parse_command_line(shlex.split(meant))
    assert args.command == name


def test_a_misspelt_flag_still_gets_the_nearest_one(capsys) -> None:
    """Only mapped flags are rewritten: a typo keeps its "did you mean", and a flag neither
    mapped nor near one its --help line."""
    with pytest.raises(SystemExit):
        parse_command_line(["eval", "--polcy", "p", "--out", "o"])
    assert "--polcy; did you mean --policy?" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_command_line(["compare", "a", "b", "--destination", "c"])
    assert "`so101-sim compare --help` lists its arguments" in capsys.readouterr().err
