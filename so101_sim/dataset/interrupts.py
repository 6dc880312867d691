"""Ctrl-C and SIGTERM while a dataset is being written: end with a finalized dataset.

Every writer of a dataset (``record``, ``eval --save-rollouts``) installs ``Interrupts``: the
signal becomes a KeyboardInterrupt, deferred while an episode is being saved; one that Python
dropped (raised inside a garbage-collection callback) is raised again by ``check`` at the
loop's next turn. ``train`` (during start-up) and ``curve`` (between checkpoints) install it
too, and ``eval`` without a dataset for whichever of the two still has Python's default.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from typing import Any


class Interrupts:
    """Turns SIGINT/SIGTERM into KeyboardInterrupt, deferred while an episode is being saved,
    so that Ctrl-C ends a run with a finalized dataset and a checkpoint. `signals`: those it
    turns (the others keep their handlers)."""

    def __init__(self, signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.signals = signals
        self.critical = False
        self.pending: int | None = None
        self.seen: int | None = None  # the last signal handled, raised or deferred
        self._old: dict[int, Any] = {}

    @classmethod
    def of_defaults(cls) -> Interrupts:
        """For those of SIGINT and SIGTERM still at Python's default (KeyboardInterrupt, a
        silent kill): a handler the caller or Ray installed stays theirs."""
        usual = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
        return cls(tuple(s for s, h in usual.items() if signal.getsignal(s) is h))

    def _handler(self, signum: int, frame: Any) -> None:
        self.seen = signum
        if self.critical:
            self.pending = signum
        else:
            raise KeyboardInterrupt(f"signal {signum}")

    def check(self) -> None:
        """Raise again for a signal already handled. Python prints and drops an exception
        raised in a weakref callback or ``__del__`` (garbage collection runs them anywhere), so
        a Ctrl-C that lands there is lost; a loop that calls this between units of work still
        stops at the next one."""
        if self.seen is not None:
            raise KeyboardInterrupt(f"signal {self.seen}")

    def install(self) -> None:
        for sig in self.signals:
            with suppress(ValueError):  # not the main thread: leave signals alone
                self._old[sig] = signal.signal(sig, self._handler)

    def ignore(self) -> None:
        """While closing: a second Ctrl-C must not interrupt the checkpoint."""
        for sig in self._old:
            signal.signal(sig, signal.SIG_IGN)

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()

    @contextmanager
    def deferred(self) -> Iterator[None]:
        self.critical = True
        try:
            yield
        finally:
            self.critical = False
        if self.pending is not None:
            signum, self.pending = self.pending, None
            raise KeyboardInterrupt(f"signal {signum}")
