"""The Ray backend: one Ray actor per worker, on a local Ray runtime or a cluster.

This follows how rollouts scale in this field (RLlib's env runners, TorchRL's Ray eval
workers are actors, one env set each). Each actor asks for one CPU (an equal share when the
cluster has fewer CPUs than workers, as the local backend oversubscribes a small machine),
actors are spread over the nodes, and each builds its service, hence its GL context, inside
itself after it starts. Replies (frames, encoded episodes) travel through Ray's object store.
Actors are not restarted by Ray: a dead or hung one is killed and replaced here, and the
calls it owed come back as ``died`` so the caller re-runs that work. When a node leaves, its
actors' replacements run on the remaining nodes without a CPU reservation (oversubscribed),
so the run finishes there. Connecting is bounded and interruptible (``ray_connect``), and
every wait here is cut into 1 s slices so Ctrl-C and SIGTERM are handled at every stage.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import signal
import sys
import time
import traceback
from collections import deque
from collections.abc import Callable
from typing import Any

from so101_sim.utils.devices import cpu_count
from so101_sim.workers.base import RAY_INSTALL_HINT, PoolInfo, Reply, WorkerPool
from so101_sim.workers.ray_connect import (
    RayAddressError,
    bounded_init,
    connect_timeout,
    exit_on_sigterm,
    init_holding_signals,
    probe_address,
)

#: Environment the actors need, copied from the driver: GL backend, offline hub, threads.
FORWARDED_ENV = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "HF_HUB_OFFLINE", "OMP_WAIT_POLICY")


def import_ray() -> Any:
    """The ``ray`` module, or an error that says how to install it. SIGTERM exits cleanly
    from here on: the import alone takes seconds on a busy machine."""
    exit_on_sigterm()
    try:
        import ray
    except ImportError:
        raise RuntimeError(f"--backend ray needs Ray, which is not installed here; install it "
                           f"with: {RAY_INSTALL_HINT}; or use --backend local") from None
    except BaseException:
        forget_ray_shutdown()
        raise
    return ray


def forget_ray_shutdown() -> None:
    """After a signal cut ``import ray`` short: Ray has started nothing, but its worker
    module may have registered ``ray.shutdown`` at exit already, which on the half-imported
    package prints a traceback as the process ends. Unregister it, also when the worker
    module's own import was the one cut short (then it is no longer in sys.modules: CI once
    printed ``partially initialized module 'ray' has no attribute '_private'``)."""
    worker = sys.modules.get("ray._private.worker")
    if worker is not None and hasattr(worker, "shutdown"):
        atexit.unregister(worker.shutdown)
        return
    import gc

    for obj in gc.get_objects():  # rare path: the function object is only reachable here
        if (callable(obj) and getattr(obj, "__name__", None) == "shutdown"
                and getattr(obj, "__module__", None) == "ray._private.worker"):
            atexit.unregister(obj)


class WorkerActor:
    """What runs inside each actor: the service, and calls on it by name."""

    def __init__(self, factory: Callable[[], Any]) -> None:
        self.service = factory()

    def ready(self) -> str:
        import ray

        return ray.get_runtime_context().get_node_id()

    def call(self, method: str, args: tuple) -> tuple[str, Any]:
        try:
            return "ok", getattr(self.service, method)(*args)
        except Exception as exc:
            return "error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"

    def shutdown(self) -> None:
        close = getattr(self.service, "close", None)
        if close is not None:
            close()


def connect(address: str | None, workers: int) -> bool:
    """Join the cluster at `address` (``"auto"`` or ``host:port``), or start a local runtime
    when `address` is None; reuse a connection this process already has. True if this call
    connected (so ``close`` should disconnect)."""
    ray = import_ray()
    if ray.is_initialized():
        return False
    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                              "logging_level": logging.WARNING}
    try:
        if address is None:  # Ctrl-C / SIGTERM wait until it has started, then stop cleanly
            caught = init_holding_signals(lambda: ray.init(address="local",
                                                           num_cpus=cpu_count(), **kwargs))
            if caught is not None:
                ray.shutdown()
                if caught == signal.SIGINT:
                    raise KeyboardInterrupt
                sys.exit(caught)
        else:  # bounded, and Ctrl-C / SIGTERM work while it waits (ray_connect)
            timeout = connect_timeout()
            probe_address(address, timeout)
            bounded_init(lambda: ray.init(address=address, **kwargs), address, timeout)
    except RayAddressError:
        raise  # one line already
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = address or "a new local runtime"
        raise RuntimeError(f"could not connect to Ray at {where}: {exc}; start a cluster with "
                           "`ray start --head` (then --ray-address auto), or leave out "
                           "--ray-address to start a local runtime") from None
    return True


class RayPool(WorkerPool):
    """N actors, one service each; replies through Ray's object store."""

    def __init__(self, factory: Callable[[], Any], n: int, *, address: str | None, name: str,
                 timeout_s: float = 600.0, start_timeout_s: float = 300.0,
                 log: Callable[[str], None] = print) -> None:
        self.ray = import_ray()
        self.factory, self.name, self.address = factory, name, address
        self.timeout_s, self.start_timeout_s = timeout_s, start_timeout_s
        self.log = log
        self._owns_runtime = connect(address, n)
        self._actors: list[Any] = [None] * n
        self._nodes: list[str] = [""] * n
        self._calls: list[deque[tuple[Any, str, tuple]]] = [deque() for _ in range(n)]
        self._since: dict[int, float] = {}
        self._restarts = 0
        try:
            self.cpus = self._cpu_share(n, log)
            env = {k: os.environ[k] for k in FORWARDED_ENV if k in os.environ}
            self._options = {"num_cpus": self.cpus, "max_restarts": 0,
                             "scheduling_strategy": "SPREAD",
                             "runtime_env": {"env_vars": env} if env else None}
            self._remote = self.ray.remote(WorkerActor)
            self._cls = self._remote.options(**self._options)
            for i in range(n):
                self._actors[i] = self._cls.remote(factory)
            for i in range(n):
                self._await_ready(i)
        except BaseException:
            self.close()
            raise

    def _cpu_share(self, n: int, log: Callable[[str], None]) -> float:
        deadline = time.monotonic() + 60  # a fresh runtime reports its CPUs after a moment
        while (free := float(self.ray.available_resources().get("CPU", 0.0))) < 0.01 * n:
            if time.monotonic() > deadline:
                break
            time.sleep(0.5)
        if free >= n:
            return 1.0
        if free < 0.01 * n:
            raise RuntimeError(f"the Ray cluster has {free:g} free CPUs; {n} workers need at "
                               "least one between them: free some, add nodes, or use fewer "
                               "workers")
        share = int(100 * free / n) / 100
        log(f"so101-sim: {n} Ray workers on {free:g} free CPUs: {share:g} CPU each "
            "(oversubscribed, like the local backend on a small machine)")
        return share

    def _await_ready(self, i: int) -> None:
        ray = self.ray
        ref, deadline = self._actors[i].ready.remote(), time.monotonic() + self.start_timeout_s
        try:  # in 1 s slices: Ctrl-C and SIGTERM are handled between them
            while not ray.wait([ref], timeout=min(1.0, max(0.0, deadline - time.monotonic())))[0]:
                if time.monotonic() >= deadline:
                    raise ray.exceptions.GetTimeoutError()
            self._nodes[i] = ray.get(ref)
        except ray.exceptions.GetTimeoutError:
            raise RuntimeError(f"Ray worker {self.name}-{i} was not running after "
                               f"{self.start_timeout_s:.0f} s (cluster resources: "
                               f"{ray.available_resources()}); the cluster may lack CPUs for "
                               "all the workers") from None
        except ray.exceptions.RayError as exc:
            raise RuntimeError(f"Ray worker {self.name}-{i} could not start its "
                               f"{type(self.factory).__name__}: {exc}") from None

    @property
    def size(self) -> int:
        return len(self._actors)

    def submit(self, worker: int, method: str, *args: Any) -> None:
        if not self._calls[worker]:
            self._since[worker] = time.monotonic()
        ref = self._actors[worker].call.remote(method, args)
        self._calls[worker].append((ref, method, args))

    def pending(self, worker: int) -> int:
        return len(self._calls[worker])

    def collect(self, wait_all: bool = False, wake: Any = None) -> list[Reply]:
        # `wake` (a forward finishing) is for local pools: eval runs one forward at a time here
        ray = self.ray
        out: list[Reply] = []
        while self.busy and (wait_all or not out):
            # Only the oldest call of each actor: an actor answers its calls in order.
            heads = {self._calls[i][0][0]: i for i in self._since}
            deadline = min(self._since.values()) + self.timeout_s
            ready, rest = ray.wait(list(heads), num_returns=1,  # short: signals run between
                                   timeout=min(1.0, max(0.0, deadline - time.monotonic())))
            if ready and rest:  # and whatever else is done already: fuller policy batches
                ready += ray.wait(rest, num_returns=len(rest), timeout=0)[0]
            for ref in ready:
                i = heads[ref]
                try:
                    status, payload = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    out += self._died(i, f"{type(exc).__name__}: {str(exc).splitlines()[0]}")
                    continue
                _, method, args = self._calls[i].popleft()
                if status == "ok":
                    out.append(Reply(i, method, args, value=payload))
                else:
                    out.append(Reply(i, method, args, error=str(payload)))
                if self._calls[i]:
                    self._since[i] = time.monotonic()
                else:
                    self._since.pop(i)
            now = time.monotonic()
            for i, t in list(self._since.items()):
                if now - t > self.timeout_s:
                    out += self._died(i, f"no reply within {self.timeout_s:.0f} s")
        return out

    def _died(self, i: int, why: str) -> list[Reply]:
        lost = [(method, args) for _, method, args in self._calls[i]]
        msg = f"Ray worker {self.name}-{i} on node {self._nodes[i][:8]} died: {why}"
        self.restart(i)
        return [Reply(i, method, args, died=msg) for method, args in lost]

    def restart(self, worker: int) -> None:
        self._kill(worker)
        self._calls[worker].clear()
        self._since.pop(worker, None)
        self._restarts += 1
        for attempt in range(3):  # a node just lost may still be listed for a moment
            cls = self._cls
            if float(self.ray.available_resources().get("CPU", 0.0)) < self.cpus:
                # the cluster lost CPUs (a node left): run on the rest, oversubscribed
                self.log(f"so101-sim: Ray worker {self.name}-{worker} restarts without a CPU "
                         "reservation: the cluster has fewer free CPUs than it started with "
                         "(a node left?); the remaining nodes are oversubscribed")
                cls = self._remote.options(**{**self._options, "num_cpus": 0})
            self._actors[worker] = cls.remote(self.factory)
            try:
                self._await_ready(worker)
                return
            except RuntimeError:
                self._kill(worker)
                if attempt == 2:
                    raise
                time.sleep(2.0)

    def info(self) -> PoolInfo:
        return PoolInfo("ray", self.size, list(self._nodes), self.cpus, self.address,
                        self._restarts, self.start_s)

    def _kill(self, i: int) -> None:
        if self._actors[i] is not None:
            with contextlib.suppress(Exception):
                self.ray.kill(self._actors[i], no_restart=True)
            self._actors[i] = None

    def close(self) -> None:
        idle = [a for a, calls in zip(self._actors, self._calls, strict=True)
                if a is not None and not calls]
        with contextlib.suppress(Exception):  # let idle services clean up; never wait long
            self.ray.wait([a.shutdown.remote() for a in idle], num_returns=len(idle),
                          timeout=5)
        for i in range(self.size):
            self._kill(i)
            self._calls[i].clear()
        self._since.clear()
        if self._owns_runtime and self.ray.is_initialized():
            self.ray.shutdown()
            self._owns_runtime = False
