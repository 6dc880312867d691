"""`so101-sim --version`: the versions a result depends on, in one line for a bug report."""

from __future__ import annotations

import argparse
from typing import Any

from so101_sim.utils.versions import software_versions


def version_line() -> str:
    """so101-sim's version and its dependencies', read from the installed distributions
    (nothing heavy is imported)."""
    found = software_versions()
    own = found.pop("so101-sim") or "(not installed)"
    python = found.pop("python")
    deps = ", ".join(f"{d} {v or 'not installed'}" for d, v in found.items())
    return f"so101-sim {own} ({deps}; Python {python})"


class ShowVersion(argparse.Action):
    """Like argparse's ``version`` action, but the line is read only when asked for (the
    look-ups take ~25 ms) and printed unwrapped."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS,
                 help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: Any, values: Any,
                 option_string: str | None = None) -> None:
        print(version_line())
        parser.exit()
