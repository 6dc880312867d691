"""`so101-sim --version`: the versions a result depends on, in one line for a bug report."""

from __future__ import annotations

import argparse
import platform
from importlib import metadata
from typing import Any

#: Distributions whose versions change what the suite computes (physics, policy, env API).
DEPENDENCIES = ("mujoco", "lerobot", "torch", "gymnasium")


def _installed(dist: str) -> str:
    try:
        return f"{dist} {metadata.version(dist)}"
    except metadata.PackageNotFoundError:
        return f"{dist} not installed"


def version_line() -> str:
    """so101-sim's version and its dependencies', read from the installed distributions
    (nothing heavy is imported)."""
    found = ", ".join(_installed(d) for d in DEPENDENCIES)
    return f"{_installed('so101-sim')} ({found}; Python {platform.python_version()})"


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
