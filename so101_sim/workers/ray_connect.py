"""Reaching a Ray cluster in bounded time, and interruptibly.

``ray.init(address=...)`` against an address where no cluster answers retries inside Ray's
C++ core for a long time, printing GCS warnings, and Python's signal handlers (Ctrl-C,
SIGTERM) only run once it returns. So before anything is written the address is probed with
a plain TCP connection (``probe_address``: refused or silent -> one line that says how to
start a head node), and ``ray.init`` itself runs in a helper thread while this one waits in
short slices (``bounded_init``): Ctrl-C and SIGTERM work, and the wait ends after
``connect_timeout()`` seconds (``--ray-connect-timeout``, or the environment variable below).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

CONNECT_TIMEOUT_ENV = "SO101_SIM_RAY_CONNECT_TIMEOUT"
DEFAULT_CONNECT_TIMEOUT_S = 30.0
CURRENT_CLUSTER = Path("/tmp/ray/ray_current_cluster")  # where `ray start` records its address


class RayAddressError(RuntimeError):
    """The Ray address is invalid, or no cluster answers there in time (one line)."""


def connect_timeout() -> float:
    """Seconds to wait for a Ray cluster (``SO101_SIM_RAY_CONNECT_TIMEOUT``, default 30)."""
    raw = os.environ.get(CONNECT_TIMEOUT_ENV, "")
    if not raw:
        return DEFAULT_CONNECT_TIMEOUT_S
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not 0 < value <= 3600:
        raise RayAddressError(f"{CONNECT_TIMEOUT_ENV}={raw!r} (--ray-connect-timeout) is "
                              "invalid; expected seconds in (0, 3600], e.g. 30")
    return value


def _start_hint(port: int | str) -> str:
    return (f"start a head node there with `ray start --head --port {port}` (or pass the "
            "address of a running cluster; without --ray-address a local runtime is started)")


def resolve_address(address: str) -> tuple[str, int] | None:
    """(host, port) of `address`: ``host:port``, ``ray://host:port``, or ``auto`` (RAY_ADDRESS,
    else the cluster the last ``ray start`` here recorded; None when neither says: Ray then
    looks for a running cluster itself)."""
    given = address
    if address == "auto":
        address = os.environ.get("RAY_ADDRESS", "")
        if not address and CURRENT_CLUSTER.is_file():
            address = CURRENT_CLUSTER.read_text().strip()
        if not address:
            return None
    address = address.partition("://")[2] or address  # ray://host:port: probe host:port
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise RayAddressError(f"--ray-address {given} is invalid; expected HOST:PORT (e.g. "
                              "127.0.0.1:6379) or auto")
    return host, int(port)


def probe_address(address: str, timeout_s: float | None = None) -> None:
    """Refuse in one line, within `timeout_s`, an address where nothing accepts a connection
    (retried meanwhile: a head node may be starting)."""
    timeout_s = connect_timeout() if timeout_s is None else timeout_s
    resolved = resolve_address(address)
    if resolved is None:
        return  # ray.init(address="auto") searches, bounded by bounded_init
    host, port = resolved
    deadline = time.monotonic() + timeout_s
    why = "no answer"
    while True:
        left = deadline - time.monotonic()
        try:
            socket.create_connection((host, port), timeout=max(0.1, min(left, 2.0))).close()
            return
        except OSError as exc:
            why = exc.strerror or type(exc).__name__
        if time.monotonic() >= deadline:
            raise RayAddressError(f"no Ray cluster answers at --ray-address {address} "
                                  f"({host}:{port}: {why.lower()}, for {timeout_s:g} s); "
                                  + _start_hint(port))
        time.sleep(min(0.5, max(0.0, deadline - time.monotonic())))


def bounded_init(init: Callable[[], Any], address: str, timeout_s: float) -> None:
    """Join a cluster: run `init` (``ray.init``) in a helper thread and wait for it here in
    short slices, at most `timeout_s`; Ctrl-C and SIGTERM end the wait at once (SIGTERM
    exits, as Ray's own handler does)."""
    exit_on_sigterm()
    box: dict[str, BaseException] = {}

    def run() -> None:
        try:
            init()
        except BaseException as exc:  # handed to the waiting thread
            box["error"] = exc

    worker_logger = logging.getLogger("ray._private.worker")
    level = worker_logger.level
    worker_logger.setLevel(logging.ERROR)  # "SIGTERM handler is not set ... not the main thread"
    thread = threading.Thread(target=run, name="so101-ray-connect", daemon=True)
    try:
        thread.start()
        deadline = time.monotonic() + timeout_s
        while thread.is_alive() and time.monotonic() < deadline:
            thread.join(0.2)
    finally:
        with contextlib.suppress(Exception):
            worker_logger.setLevel(level)
    if thread.is_alive():
        raise RayAddressError(f"Ray did not connect to {address} within {timeout_s:g} s "
                              "(--ray-connect-timeout); is it a Ray cluster's GCS port? "
                              + _start_hint(address.rpartition(":")[2] if ":" in address
                                            else 6379))
    if "error" in box:
        raise box["error"]


def init_holding_signals(init: Callable[[], Any]) -> int | None:
    """Start a local runtime: run `init` here, in the main thread (Ray's processes die with
    the thread that started them), with Ctrl-C and SIGTERM held until it returns: a runtime
    cut short leaves processes behind. Returns the signal that came meanwhile (the caller
    shuts the runtime down and stops), or None."""
    if threading.current_thread() is not threading.main_thread():
        init()
        return None
    pending: list[int] = []

    def hold(signum: int, frame: Any) -> None:
        if not pending:
            print("so101-sim: stopping as soon as the Ray runtime has started (one cut short "
                  "leaves processes behind)", file=sys.stderr, flush=True)
        pending.append(signum)

    old_int = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGTERM, hold)
    if old_int is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, hold)
    utils = sys.modules.get("ray._private.utils")
    ray_sets = getattr(utils, "set_sigterm_handler", None)
    if ray_sets is not None:  # ray.init installs its own SIGTERM handler early: not yet
        utils.set_sigterm_handler = lambda handler: None  # type: ignore[union-attr]
    try:
        init()
    finally:
        if ray_sets is not None:
            utils.set_sigterm_handler = ray_sets  # type: ignore[union-attr]
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, _exit_on_signal)  # what Ray's init would have set
    return pending[0] if pending else None


def exit_on_sigterm() -> None:
    """From here on SIGTERM ends this process as Ray's own handler does: exit 15, with
    ``finally`` blocks run (the run folder is cleaned up). Only the main thread can set it.
    Called before ``import ray`` too, which takes seconds on a busy machine: a SIGTERM there
    met Python's default action and the process died at once (exit -15, the folder left)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _exit_on_signal)


_RECEIVED: list[int] = []  # the signals `_exit_on_signal` turned into SystemExit


def _exit_on_signal(signum: int, frame: Any) -> None:
    _RECEIVED.append(signum)
    sys.exit(signum)


@contextlib.contextmanager
def signal_exit_code() -> Iterator[None]:
    """Keep exit code 15 for a SIGTERM that came while Ray waited in C++ (``ray.wait``,
    ``ray.get``): Ray's signal check there catches the handler's ``SystemExit(15)`` and raises
    ``SystemExit(1)`` in its place, so the exit code depended on where the signal landed."""
    try:
        yield
    except SystemExit as exc:
        if _RECEIVED and exc.code != _RECEIVED[0]:
            raise SystemExit(_RECEIVED[0]) from None
        raise
