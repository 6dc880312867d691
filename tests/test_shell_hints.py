"""Commands that errors suggest stay one shell word per argument for paths with spaces.

A run folder under "My Drive" or "rün 1" is ordinary; a hint printed as `--out /x/a b
--resume` splits into two words when pasted and fails on another error."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from so101_sim.cli import main
from so101_sim.cli.parser import parse_command_line
from so101_sim.harness.compare import missing_info_reason
from so101_sim.harness.curve import run_checkpoints
from so101_sim.harness.export import model_card
from so101_sim.train.checkpoint import TRAIN_INFO, other_kind

SPACED = "/tmp/so101 hints/rün 1"
SHIPPED = Path(__file__).parent.parent / "policy" / "pick_place_diffusion"


def suggested(line: str, start: str, end: str | None = None) -> list[str]:
    """The words of the last command in `line` that begins at `start` (up to `end`)."""
    text = line[line.rindex(start):]
    return shlex.split(text[:text.index(end)] if end else text)


@pytest.mark.parametrize(("argv", "meant"), [
    (["curve", "--run", SPACED, "--episodes", "2"], ["curve", SPACED, "--episodes", "2"]),
    (["eval", f"--policy.path={SPACED}", "--out", "o"], ["eval", "--policy", SPACED, "--out", "o"]),
])
def test_cli_hints_quote_paths(argv: list[str], meant: list[str], capsys) -> None:
    """The positional hint printed `so101-sim curve /tmp/so101 hints/rün 1 ...` unquoted;
    pasted, it gave curve three positionals."""
    with pytest.raises(SystemExit):
        parse_command_line(argv)
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert suggested(last, f"so101-sim {argv[0]} ") == ["so101-sim", *meant]
    assert parse_command_line(meant).command == argv[0]


def test_resume_hint_of_an_interrupted_eval_quotes_its_folder(tmp_path: Path) -> None:
    run = tmp_path / "évàl 1"
    run.mkdir()
    (run / "episodes.jsonl").write_text("")
    reason = missing_info_reason(run)
    assert suggested(reason, "--out ") == ["--out", str(run), "--resume"]


def test_a_dataset_given_as_a_policy_names_train_with_its_folder_quoted(tmp_path: Path) -> None:
    data = tmp_path / "my data"
    (data / "meta").mkdir(parents=True)
    (data / "meta" / "info.json").write_text(json.dumps({"codebase_version": "v3.0"}))
    words = suggested(other_kind(data), "so101-sim train", "`")
    assert words == ["so101-sim", "train", "--dataset", str(data), "--out", "RUN"]


def test_curve_on_a_checkpoint_names_its_run_quoted(tmp_path: Path, capsys) -> None:
    run = tmp_path / "rün 1"
    checkpoint = run / "checkpoints" / "step_000004" / "pretrained_model"
    checkpoint.mkdir(parents=True)
    (checkpoint / "config.json").write_text("{}")
    (checkpoint / "model.safetensors").write_bytes(b"")
    if not run_checkpoints(run):
        pytest.fail(f"the fixture is not a run to curve: {sorted(run.rglob('*'))}")
    assert main(["curve", str(checkpoint)]) != 0
    err = capsys.readouterr().err
    assert suggested(err, "so101-sim curve", "`") == ["so101-sim", "curve", str(run)]


def test_model_card_eval_line_quotes_the_folder_name() -> None:
    info = json.loads((SHIPPED / TRAIN_INFO).read_text())
    card = model_card(info, None, [], "a CPU", name="my policy")
    assert suggested(card, "so101-sim eval", "`")[:4] == [
        "so101-sim", "eval", "--policy", "policy/my policy"]
