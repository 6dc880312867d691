"""Counts in the lines a user reads: "1 seed", "2 seeds", not "1 seeds"."""

from __future__ import annotations

__all__ = ["counted", "seed_span"]


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """`n` and `noun`, plural unless n is 1 (`plural` for irregular nouns)."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def seed_span(first: int, last: int) -> str:
    """"seeds 100000..100049", or "seed 100000" for one."""
    return f"seed {first}" if first == last else f"seeds {first}..{last}"
