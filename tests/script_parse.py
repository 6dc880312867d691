"""Parse scripts' command lines with each script's own argparse parser, and run nothing.

    python tests/script_parse.py < lines.json    # [[script, [arg, ...]], ...]

Prints a JSON list with one entry per line: null where the script's parser took the line, or
the last line of what it said when it refused it. Each script's ``main()`` runs until its
outermost ``parse_known_args`` (which ``parse_args`` calls) has finished, and stops there, so
none of its work starts. Runs in a process of its own because the scripts change process
state as they start (``so101-sim train`` through ``benchmarks/gpu/train_without_pyav.py`` says
the process is a command's own), which a test worker must not inherit.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
from pathlib import Path

from script_loader import load_script

ROOT = Path(__file__).resolve().parents[1]


class Parsed(BaseException):
    """Raised where the script's work would start (not an Exception: a script's own error
    handling must not catch it)."""


def stop_after_parsing() -> None:
    """Make the outermost parse of every ArgumentParser end in Parsed, or in argparse's error
    for arguments it did not take (a subcommand's parse inside its parent's goes on)."""
    parse_known_args = argparse.ArgumentParser.parse_known_args
    depth = 0

    def parse_then_stop(self, args=None, namespace=None):
        nonlocal depth
        depth += 1
        try:
            parsed, extras = parse_known_args(self, args, namespace)
        finally:
            depth -= 1
        if depth:
            return parsed, extras
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        raise Parsed

    argparse.ArgumentParser.parse_known_args = parse_then_stop


def refusal(script: str, args: list[str], modules: dict) -> str | None:
    """None if `script` takes `args`, else the last line it printed refusing them."""
    sys.argv = [script, *args]
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            if script not in modules:  # its folder first on the path, as when it is run
                sys.path.insert(0, str((ROOT / script).parent))
                modules[script] = load_script(ROOT / script, register=True)
            modules[script].main()
    except Parsed:
        return None
    except SystemExit:
        return (err.getvalue().strip().splitlines() or ["(nothing)"])[-1]
    return "it returned without parsing its arguments"


def main() -> None:
    lines = json.load(sys.stdin)
    stop_after_parsing()
    modules: dict = {}
    print(json.dumps([refusal(script, args, modules) for script, args in lines]))


if __name__ == "__main__":
    main()
