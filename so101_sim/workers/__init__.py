"""One seam for "run envs in workers", with a local and a Ray backend.

A pool holds N workers. Each worker builds one *service* object inside itself after it starts
(an env with its own GL context, or an episode recorder), from a picklable factory; the driver
calls the service's methods by name (``submit``) and picks up the answers (``collect``). A
call that raises comes back as an error and the worker stays usable; a worker that dies or
hangs is replaced, and every call it still owed comes back as ``died`` so the caller can run
that work again. ``eval`` and ``record`` use only this module: which backend runs is a
setting, never a code path of theirs.

Backends: ``local``, forkserver processes on this machine (``so101_sim.workers.local``), and
``ray``, one Ray actor per worker on a local Ray runtime or a cluster
(``so101_sim.workers.ray_pool``; Ray is an optional extra: ``pip install 'so101-sim[ray]'``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from so101_sim.workers.base import (
    BACKENDS,
    RAY_INSTALL_HINT,
    PoolInfo,
    Reply,
    WorkerDied,
    WorkerPool,
    check_backend,
)


def start_pool(factory: Callable[[], Any], n: int, *, backend: str = "local",
               ray_address: str | None = None, name: str = "so101-worker",
               preload: tuple[str, ...] = (), timeout_s: float = 600.0,
               start_timeout_s: float = 300.0,
               log: Callable[[str], None] | None = None) -> WorkerPool:
    """Start `n` workers, each running ``factory()`` once it is up; wait until all are ready.

    `preload`: modules the local fork server imports once for all workers. `ray_address`:
    ``None`` starts a local Ray runtime, ``"auto"`` or ``host:port`` joins a running cluster.
    `timeout_s`: a call running longer than this counts as a hung worker.
    """
    check_backend(backend, ray_address)
    if n < 1:
        raise ValueError(f"n={n} workers is invalid; expected at least 1")
    t0 = time.perf_counter()
    pool: WorkerPool
    if backend == "local":
        from so101_sim.workers.local import LocalPool

        pool = LocalPool(factory, n, name=name, preload=preload, timeout_s=timeout_s,
                         start_timeout_s=start_timeout_s)
    else:
        from so101_sim.workers.ray_pool import RayPool

        pool = RayPool(factory, n, address=ray_address, name=name, timeout_s=timeout_s,
                       start_timeout_s=start_timeout_s, log=log or print)
    pool.start_s = time.perf_counter() - t0
    return pool


__all__ = ["BACKENDS", "RAY_INSTALL_HINT", "PoolInfo", "Reply", "WorkerDied", "WorkerPool",
           "check_backend", "start_pool"]
