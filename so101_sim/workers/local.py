"""The local backend: one forkserver process per worker, method calls over a pipe.

Why our own processes rather than Gymnasium's ``AsyncVectorEnv`` or a ``ProcessPoolExecutor``:
a worker keeps its env (and GL context) for the whole run, a call can be a whole action chunk
or a whole episode, and a worker that dies or hangs is replaced on its own while the others
keep their work. Workers start with ``forkserver`` (never ``fork``: the parent may hold torch's
threads or a GL context) and build their service after they start. A worker ignores Ctrl-C
(the parent decides what to keep) and exits when the parent's end of its pipe closes, so a
parent killed with SIGKILL leaves no worker behind.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import socket
import sys
import time
import traceback
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import Connection, wait
from typing import Any

from so101_sim.utils.environ import environ_set
from so101_sim.workers.base import PoolInfo, Reply, WorkerPool

#: Imported by the fork server after every pool's preloads, never here (workers.server_init).
SERVER_INIT = "so101_sim.workers.server_init"


def server_preload(preload: tuple[str, ...]) -> list[str]:
    """What the fork server imports: `preload`, the command's own module (``script_module``),
    then ``SERVER_INIT``."""
    script = script_module()
    mods = [*preload, *([script] if script and script not in preload else [])]
    return [m for m in mods if m != SERVER_INIT] + [SERVER_INIT]


def _worker_main(conn: Connection, factory: Callable[[], Any]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group
    with contextlib.suppress(EOFError, BrokenPipeError, ConnectionResetError):
        _serve(conn, factory)


def _serve(conn: Connection, factory: Callable[[], Any]) -> None:
    try:
        service = factory()
    except Exception as exc:
        conn.send(("fatal", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))
        return
    conn.send(("ready", socket.gethostname()))
    try:
        while (msg := conn.recv()) is not None:
            method, args = msg
            try:
                conn.send(("ok", getattr(service, method)(*args)))
            except Exception as exc:
                conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))
    finally:
        close = getattr(service, "close", None)
        if close is not None:
            with contextlib.suppress(Exception):
                close()


def ensure_fork_server() -> None:
    """Start this process's fork server if it is not running, importing with this process's
    ``sys.path``.

    Python 3.12 runs the server as ``python -c`` and drops the ``sys.path`` it is handed, so
    the server and every worker forked from it would import with the current directory first:
    run from another checkout, the workers would run that checkout's so101_sim (or a stray
    ``mujoco.py``) beside this process's own, silently. The server starts with
    PYTHONSAFEPATH (no current directory) and this process's ``sys.path`` as PYTHONPATH.
    """
    from multiprocessing import forkserver

    paths = os.pathsep.join(os.path.abspath(p or os.curdir) for p in sys.path)  # "" = cwd
    with environ_set({"PYTHONSAFEPATH": "1", "PYTHONPATH": paths}):
        forkserver.ensure_running()


def script_module() -> str | None:
    """The module the running command's ``__main__`` comes from (``lerobot.scripts.lerobot_eval``
    for the ``lerobot-eval`` console script or ``python -m lerobot.scripts.lerobot_eval``),
    else None.

    Every process forked from the fork server runs the main module again first (as
    ``__mp_main__``), and CPython 3.12's server never imports it for them (``forkserver`` keeps
    a ``main_path`` key that ``spawn`` names ``init_main_from_path``), so each of
    lerobot-eval's env workers imported torch and lerobot on its own. Preloaded once in the
    server, the module's imports are already there when a worker runs it."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None:  # `python -m NAME`: workers run NAME again (a package's __main__ not)
        name = spec.name
        return None if name == "__main__" or name.endswith(".__main__") else name
    module = getattr(getattr(main, "main", None), "__module__", None)  # a console script
    return module if isinstance(module, str) and module != "__main__" else None


def start_fork_server(preload: tuple[str, ...]) -> None:
    """Start this process's fork server now, importing `preload`, without waiting for it.

    A caller that knows it will start workers later can let the server import while it does
    its own start-up. The server and its modules are then fixed for the process: a later
    pool's preload is not imported by the server (its workers import what they lack), and
    workers inherit the environment as it is now.
    """
    mp.get_context("forkserver").set_forkserver_preload(server_preload(preload))
    ensure_fork_server()


def check_main_reloadable() -> None:
    """Refuse, in one line, a program whose ``__main__`` the workers cannot run again: each
    forkserver child re-runs it from its path, and a script read from stdin (`python - <<EOF`)
    names '<stdin>', so every worker died on FileNotFoundError under its own traceback."""
    from multiprocessing.spawn import get_preparation_data

    path = get_preparation_data("check").get("init_main_from_path")
    if path is not None and not os.path.isfile(path):
        raise RuntimeError(
            f"so101_sim's env workers start with multiprocessing's forkserver, which runs this "
            f"program's __main__ again from its file, and {path!r} is not a file (a script "
            "read from stdin, as `python - <<EOF` does): save the script and run `python "
            "script.py`, or pass it with `python -c`")


class LocalPool(WorkerPool):
    """N forkserver processes, one service each."""

    def __init__(self, factory: Callable[[], Any], n: int, *, name: str,
                 preload: tuple[str, ...] = (), timeout_s: float = 600.0,
                 start_timeout_s: float = 300.0) -> None:
        check_main_reloadable()
        self.factory, self.name = factory, name
        self.timeout_s, self.start_timeout_s = timeout_s, start_timeout_s
        self._ctx = mp.get_context("forkserver")
        # the fork server imports these once (if it is not running yet); each worker forks
        # from it ready
        self._ctx.set_forkserver_preload(server_preload(preload))
        self._procs: list[Any] = [None] * n
        self._conns: list[Connection | None] = [None] * n
        self._calls: list[deque[tuple[str, tuple]]] = [deque() for _ in range(n)]
        self._since: dict[int, float] = {}  # worker -> when its oldest pending call started
        self._restarts = 0
        try:
            for i in range(n):
                self._spawn(i)
            for i in range(n):
                self._await_ready(i)
        except BaseException:
            self.close()
            raise

    @property
    def size(self) -> int:
        return len(self._procs)

    def pid(self, i: int) -> int | None:
        return self._procs[i].pid if self._procs[i] is not None else None

    def _spawn(self, i: int) -> None:
        ensure_fork_server()  # the first worker starts it (or a new one, had it died)
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(target=_worker_main, args=(child, self.factory),
                                 name=f"{self.name}-{i}", daemon=True)
        proc.start()
        child.close()
        self._procs[i], self._conns[i] = proc, parent

    def _await_ready(self, i: int) -> None:
        conn, proc = self._conns[i], self._procs[i]
        ready = wait([conn, proc.sentinel], timeout=self.start_timeout_s)
        status, payload = "fatal", f"not ready after {self.start_timeout_s:.0f} s"
        if conn in ready:
            try:
                status, payload = conn.recv()
            except EOFError:
                payload = f"exited with code {proc.exitcode} while starting"
        elif ready:
            proc.join(timeout=5)
            payload = f"exited with code {proc.exitcode} while starting"
        if status != "ready":
            raise RuntimeError(f"worker {self.name}-{i} could not start its "
                               f"{type(self.factory).__name__}: {payload}")

    def restart(self, worker: int) -> None:
        self._kill(worker)
        self._calls[worker].clear()
        self._since.pop(worker, None)
        self._restarts += 1
        self._spawn(worker)
        self._await_ready(worker)

    def submit(self, worker: int, method: str, *args: Any) -> None:
        if not self._calls[worker]:
            self._since[worker] = time.monotonic()
        self._calls[worker].append((method, args))
        with contextlib.suppress(BrokenPipeError, OSError):  # gone: collect() reports it
            self._conns[worker].send((method, args))

    def pending(self, worker: int) -> int:
        return len(self._calls[worker])

    def collect(self, wait_all: bool = False, wake: Any = None) -> list[Reply]:
        out: list[Reply] = []
        while self.busy and (wait_all or not out):
            handles: dict[Any, int] = {}
            for i in self._since:
                handles[self._conns[i]] = i
                handles[self._procs[i].sentinel] = i
            deadline = min(self._since.values()) + self.timeout_s
            waitables = list(handles) if wake is None else [*handles, wake]
            ready = wait(waitables, timeout=max(0.0, deadline - time.monotonic()))
            woken = wake is not None and wake in ready
            ready = [h for h in ready if h is not wake]
            answered: set[int] = set()
            for h in ready:  # replies first: a worker may exit right after its last reply
                i = handles[h]
                if h is self._conns[i] and i not in answered:
                    answered.add(i)
                    out += self._receive(i)
            for h in ready:
                i = handles[h]
                if i not in answered and i in self._since:
                    answered.add(i)
                    out += self._died(i, f"it exited with code {self._procs[i].exitcode}")
            now = time.monotonic()
            for i, t in list(self._since.items()):
                if now - t > self.timeout_s:
                    out += self._died(i, f"no reply within {self.timeout_s:.0f} s")
            if woken and not wait_all:
                break
        return out

    def _receive(self, i: int) -> list[Reply]:
        """Every reply worker `i` has sent so far (at least one is waiting)."""
        out: list[Reply] = []
        conn = self._conns[i]
        while self._calls[i]:
            try:
                if out and not conn.poll():
                    break
                status, payload = conn.recv()
            except (EOFError, OSError):
                return out + self._died(i, "its pipe closed")
            method, args = self._calls[i].popleft()
            if status == "ok":
                out.append(Reply(i, method, args, value=payload))
            else:
                out.append(Reply(i, method, args, error=str(payload)))
            self._since[i] = time.monotonic()
        if not self._calls[i]:
            self._since.pop(i, None)
        return out

    def _died(self, i: int, why: str) -> list[Reply]:
        lost = list(self._calls[i])
        msg = f"worker {self.name}-{i} (pid {self.pid(i)}) died: {why}"
        self.restart(i)
        return [Reply(i, method, args, died=msg) for method, args in lost]

    def info(self) -> PoolInfo:
        return PoolInfo("local", self.size, [socket.gethostname()] * self.size,
                        restarts=self._restarts, start_s=self.start_s)

    def _kill(self, i: int) -> None:
        proc, conn = self._procs[i], self._conns[i]
        if conn is not None:
            conn.close()
        if proc is not None:
            if proc.is_alive():
                proc.kill()
            proc.join(timeout=5)
        self._procs[i], self._conns[i] = None, None

    def close(self) -> None:
        idle = [i for i, p in enumerate(self._procs)
                if p is not None and p.is_alive() and not self._calls[i]]
        for i in idle:
            with contextlib.suppress(BrokenPipeError, OSError):
                self._conns[i].send(None)
        deadline = time.monotonic() + 5
        for i in idle:
            self._procs[i].join(timeout=max(0.0, deadline - time.monotonic()))
        for i in range(self.size):
            self._kill(i)
            self._calls[i].clear()
        self._since.clear()

