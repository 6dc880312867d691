"""The commands the docs tell users to run are ones the CLI accepts as written."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COMMAND = re.compile(r"(?:\S*/)?so101-sim\s+(.*)")  # so101-sim ..., .venv/bin/so101-sim ...


def shown_commands(path: Path) -> list[str]:
    """`so101-sim` command lines of `path`: in ```bash blocks, or indented 4 spaces."""
    found, fenced, lang = [], False, ""
    text = path.read_text().replace("\\\n", " ")  # a continued command is one line
    for line in text.splitlines():
        if line.startswith("```"):
            fenced, lang = not fenced, line[3:].strip()
            continue
        shown = (fenced and lang in ("bash", "")) or (not fenced and line.startswith("    "))
        if shown and (m := COMMAND.match(line.strip().split(" #")[0])):
            found.append(m.group(1))
    return found


@pytest.mark.parametrize("doc", ["README.md", "benchmarks/README.md"])
def test_documented_commands_parse(doc: str, capsys) -> None:
    from so101_sim.cli.parser import build_parser

    commands = shown_commands(ROOT / doc)
    assert len(commands) >= 10, commands  # the docs show a command-line workflow
    parser = build_parser()
    refused = []
    for command in commands:
        try:
            parser.parse_args(shlex.split(command))
        except SystemExit:
            refused.append((command, capsys.readouterr().err.strip().splitlines()[-1]))
    assert refused == []
