"""Phrases in the lines a user reads: "1 seed", "2 seeds", not "1 seeds"; "did you mean"."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

__all__ = ["counted", "did_you_mean", "md_row", "seed_span"]


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """`n` and `noun`, plural unless n is 1 (`plural` for irregular nouns)."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def seed_span(first: int, last: int) -> str:
    """"seeds 100000..100049", or "seed 100000" for one."""
    return f"seed {first}" if first == last else f"seeds {first}..{last}"


def did_you_mean(text: str, names: Iterable[str]) -> str:
    """" (did you mean 'stack'?)" for the one of `names` close to a misspelt `text`, else ""."""
    near = difflib.get_close_matches(text, list(names), n=1)
    return f" (did you mean {near[0]!r}?)" if near else ""


def md_row(*cells: object) -> str:
    """One markdown table row; a `|` inside a cell (e.g. "mean |diff| 0.26") is escaped, where
    it would otherwise split the cell and push the rest of the row out of the table."""
    return "| " + " | ".join(str(c).replace("|", "\\|").replace("\n", " ") for c in cells) + " |"
