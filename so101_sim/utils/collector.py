"""Start-up and exit without the cyclic garbage collector walking torch's objects again.

Importing torch and lerobot's policies makes about 450,000 Python objects that live until the
process ends. CPython's full collections walk every one of them: six times during those imports
(about 1 s on the 2-core Xeon of benchmarks/README.md), and again while the interpreter tears
down at exit (``python -c "import lerobot.policies"`` takes 1.5 s to exit there, 0.3 s with
them frozen). A command-line process can pause the collector while it imports and loads, then
collect once and freeze the survivors (``gc.freeze``: never walked again). Garbage is still
collected (the one collection runs finalizers as usual), and no number a command prints
depends on it. Only the process's owner may do this (``own_process``, the ``so101-sim``
entry point): frozen objects that later become garbage cycles stay in memory, which a
library must not impose on a caller's long session.
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Iterator

__all__ = ["freeze_for_exit", "own_process", "startup_objects"]

_owned = False


def own_process() -> None:
    """Say this process is a so101-sim command: the functions below take effect."""
    global _owned
    _owned = True


@contextlib.contextmanager
def startup_objects() -> Iterator[None]:
    """Pause the collector while the block imports and loads; then collect once and freeze
    what survived. Does nothing unless ``own_process()`` was called."""
    if not _owned:
        yield
        return
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.collect()
        gc.freeze()
        if enabled:
            gc.enable()


def freeze_for_exit() -> None:
    """Collect now, then freeze the survivors so the interpreter's teardown skips them.

    Does nothing unless ``own_process()`` was called."""
    if _owned:
        gc.collect()
        gc.freeze()
