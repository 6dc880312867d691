"""The commands the docs tell users to run are ones the CLI accepts as written, and the
names they give in the package exist."""

from __future__ import annotations

import importlib
import re
import shlex
import warnings
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


DOTTED = re.compile(r"(?<![\w.])so101_sim(?:\.[A-Za-z_]\w*)+")
DOC_FILES = ("*.md", "docs/*.md", "benchmarks/**/*.md", "envs/*.toml", "policy/**/*.md",
             "policy/**/*.json", "policy/presets/*.toml")


def resolves(name: str) -> bool:
    """Whether `name` (so101_sim.module.attribute...) imports: its longest module, then
    attributes on it."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            with warnings.catch_warnings():  # the old module paths warn, and still count
                warnings.simplefilter("ignore", DeprecationWarning)
                obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_the_package_names_the_docs_give_exist() -> None:
    # the docs, model cards and preset comments; a module moved in a restructure left its old
    # name in a card and two presets before
    docs = sorted({p for pattern in DOC_FILES for p in ROOT.glob(pattern)})
    assert ROOT / "README.md" in docs and ROOT / "policy/presets/cpu.toml" in docs
    where: dict[str, list[str]] = {}  # each name is resolved once, wherever it is given
    for path in docs:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            for name in DOTTED.findall(line):
                where.setdefault(name, []).append(f"{path.relative_to(ROOT)}:{n}")
    missing = [f"{place}: {name}" for name, places in where.items() if not resolves(name)
               for place in places]
    assert missing == []
