"""The pool interface both backends implement, and the checks they share."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

from so101_sim.workers.ray_connect import probe_address

BACKENDS = ("local", "ray")
RAY_INSTALL_HINT = "pip install 'so101-sim[ray]' (or: pip install ray)"


class WorkerDied(RuntimeError):
    """A worker exited, hung past its timeout, or could not be reached."""


@dataclass
class Reply:
    """The answer to one ``submit``: a value, or why there is none."""

    worker: int
    method: str
    args: tuple
    value: Any = None
    error: str | None = None  # the call raised in the worker (traceback); the worker is fine
    died: str | None = None  # the worker died or hung; it was replaced and the call is lost

    @property
    def failed(self) -> str | None:
        """Why the call gave no value, or None when it did."""
        return self.died or self.error


@dataclass
class PoolInfo:
    """Where the workers run, for summaries and reports."""

    backend: str
    workers: int
    nodes: list[str] = field(default_factory=list)
    cpus_per_worker: float = 1.0
    address: str | None = None
    restarts: int = 0
    start_s: float = 0.0  # starting the workers (and a Ray runtime, if one was started)

    def to_dict(self) -> dict[str, Any]:
        return {"backend": self.backend, "workers": self.workers, "nodes": len(set(self.nodes)),
                "cpus_per_worker": self.cpus_per_worker, "address": self.address,
                "restarts": self.restarts, "start_s": round(self.start_s, 3)}


class WorkerPool(ABC):
    """N workers, each owning one service; the same interface on every backend."""

    start_s: float = 0.0  # seconds ``start_pool`` took

    @property
    @abstractmethod
    def size(self) -> int:
        """Number of workers."""

    @abstractmethod
    def submit(self, worker: int, method: str, *args: Any) -> None:
        """Queue ``service.method(*args)`` on `worker` (calls on one worker run in order)."""

    @abstractmethod
    def pending(self, worker: int) -> int:
        """Calls submitted to `worker` and not collected yet."""

    @abstractmethod
    def collect(self, wait_all: bool = False, wake: Any = None) -> list[Reply]:
        """Wait for at least one reply (``wait_all``: for every pending call) and return them;
        a readable `wake` handle (a connection or socket) also ends the wait, maybe with none.

        A worker found dead or hung is replaced before this returns.
        """

    @abstractmethod
    def restart(self, worker: int) -> None:
        """Replace `worker` with a fresh one (its pending calls are dropped unanswered)."""

    @abstractmethod
    def info(self) -> PoolInfo:
        """Backend, worker count, nodes used, restarts so far."""

    @abstractmethod
    def close(self) -> None:
        """Stop every worker (busy ones are killed: their work is not wanted any more)."""

    @property
    def busy(self) -> int:
        """Calls submitted and not collected yet, over all workers."""
        return sum(self.pending(i) for i in range(self.size))

    def least_busy(self) -> int:
        """The worker with the fewest pending calls (lowest index on ties)."""
        return min(range(self.size), key=self.pending)

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def check_backend(backend: str, ray_address: str | None) -> None:
    """Refuse an unknown backend, a Ray address given to the local backend, or one where no
    cluster answers (``ray_connect.probe_address``)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r} is not known; expected one of {list(BACKENDS)} "
                         "(--backend local runs processes here, --backend ray runs Ray actors)")
    if ray_address is not None and backend != "ray":
        raise ValueError(f"--ray-address {ray_address} only applies with --backend ray; add "
                         "--backend ray, or drop --ray-address")
    if ray_address is not None:  # before any folder is written: a cluster that isn't there
        probe_address(ray_address)  # is one line, in bounded time


