"""Swap a module's ``forward`` for a wrapper on the instance, and back (exact speed-ups).

The speed-ups in ``traced.py`` and ``encoder_split.py`` replace the instance ``forward`` of
lerobot modules found by class name, so parameters, state_dict names and fingerprints stay
what they were, and undoing one (for A/B timings and tests) only deletes the attribute.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import nn

__all__ = ["unwrap_forwards", "wrap_forwards"]


def _named(module: nn.Module, class_name: str) -> list[nn.Module]:
    return [m for m in module.modules() if type(m).__name__ == class_name]


def wrap_forwards(module: nn.Module, class_name: str, wrapper: type,
                  make: Callable[[nn.Module], Any]) -> int:
    """Give every `class_name` module inside `module` the forward ``make(it)`` (an instance
    of `wrapper`), unless it has one already; returns how many such modules there are."""
    found = _named(module, class_name)
    for m in found:
        if not isinstance(m.__dict__.get("forward"), wrapper):
            m.forward = make(m)
    return len(found)


def unwrap_forwards(module: nn.Module, class_name: str, wrapper: type) -> list[Any]:
    """Undo ``wrap_forwards``: the class's own forward runs again; returns the wrappers."""
    removed = []
    for m in _named(module, class_name):
        if isinstance(m.__dict__.get("forward"), wrapper):
            removed.append(m.__dict__["forward"])
            del m.forward
    return removed
