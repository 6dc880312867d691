"""Explain: the seed walkthrough re-run on your own dataset and checkpoint (``so101-sim explain``).

``explain(dataset, policy)`` traces one training example through a Diffusion Policy's real
modules (``trace`` with forward hooks from ``hooks``) and renders ``explain.html``
(``page``, ``plots``). torch loads when ``explain`` is first used, not on import.
"""

from typing import Any

from so101_sim.explain.errors import ExplainError

__all__ = ["ExplainError", "Explanation", "explain"]


def __getattr__(name: str) -> Any:
    if name in ("explain", "Explanation"):
        from so101_sim.explain import run

        return getattr(run, name)
    raise AttributeError(f"module 'so101_sim.explain' has no attribute {name!r}")
