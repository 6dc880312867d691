"""One writer per folder: a second run into a folder that a run is writing is refused.

Two runs writing one folder corrupt it silently (two datasets interleaved, two evaluations'
lines in one episodes.jsonl). Every command that writes a folder holds an exclusive
``fcntl.flock`` on a lock file inside it (``.so101.lock``) while it writes. The kernel drops
the lock when the process ends, however it ends, so a SIGKILLed run never leaves a stale
lock; the file itself names the holder (pid and command line) for the refusal message, and a
run that ends normally removes it.

``folder_lock`` is a context manager; ``hold_folder`` takes a lock for the rest of the
function decorated with ``lock_scope`` (for long functions that write several folders). On
the way out, a full disk becomes one line (``utils.disk``) and a folder this run created and
left empty (or holding only the `stub` files it wrote before failing) is removed again.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import json
import os
import shlex
import shutil
import sys
import time
from collections.abc import Callable, Iterable
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from so101_sim.utils.disk import DiskFullError, disk_full_error

LOCK_FILE = ".so101.lock"
PAUSE_ENV = "SO101_SIM_LOCK_PAUSE_S"  # test hook: wait this long after taking a lock
Again = str | Callable[[], str]  # "resume" | "rerun", or a function saying which
_held: dict[tuple[int, str], list[int]] = {}  # (pid, lock file) -> [fd, depth]: re-entrant
_scope: ContextVar[list[FolderLock] | None] = ContextVar("so101_lock_scope", default=None)


class FolderInUseError(RuntimeError):
    """Another process holds the folder's lock; the message names it."""


def _command_line() -> str:
    """This process's command, short: "so101-sim eval ...", "python -m so101_sim.cli ..."."""
    argv = list(sys.argv)
    if not argv or argv[0] in ("", "-c", "-m") or argv[0].endswith("__main__.py"):
        argv = list(getattr(sys, "orig_argv", argv)) or ["python"]
    argv[0] = Path(argv[0]).name
    text = shlex.join(argv)
    return text if len(text) <= 300 else text[:297] + "..."


def _holder(fd: int, what: str) -> tuple[str, str]:
    """('pid N (command)', what it writes) from a lock file another process holds (it writes
    them right after taking the lock: wait a moment for them)."""
    for _ in range(10):
        with contextlib.suppress(OSError, ValueError, TypeError, KeyError):
            info = json.loads(os.pread(fd, 4096, 0).decode())
            return f"pid {int(info['pid'])} ({info['command']})", str(info.get("what", what))
        time.sleep(0.05)
    return "another process (it did not say which)", what


def file_in_the_way(folder: str | Path) -> Path | None:
    """The file at `folder` or at one of its parents, which would stop its mkdir."""
    folder = Path(folder)
    return next((p for p in (folder, *folder.parents) if p.exists() and not p.is_dir()), None)


def has_content(folder: str | Path, ignore: Iterable[str] = ()) -> bool:
    """Whether `folder` holds anything besides lock files and the names in `ignore`."""
    folder = Path(folder)
    skip = {LOCK_FILE, *ignore}
    return folder.is_dir() and any(not p.name.endswith(".lock") and p.name not in skip
                                   for p in folder.iterdir())


def clear_folder(folder: str | Path) -> None:
    """Remove everything in `folder` except lock files (the folder and its lock stay)."""
    for p in Path(folder).iterdir():
        if p.name.endswith(".lock"):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


class FolderLock:
    """The exclusive lock of one folder for one writing run.

    `what` names the contents in messages ("the evaluation", "the dataset"); `again` is how
    the run continues after a full disk ("resume": the same command plus --resume, "rerun";
    or a function that says which, asked when it happens);
    `name` is the lock file (commands that may share a folder use their own); `stub`: files
    this run writes before its real work starts, removed with the folder it created when it
    fails before anything else was written.
    """

    def __init__(self, folder: str | Path, what: str, *, again: Again = "resume",
                 name: str = LOCK_FILE, stub: Iterable[str] = ()) -> None:
        self.folder = Path(folder).expanduser()
        self.what, self.again, self.name, self.stub = what, again, name, set(stub)
        self.created = False
        self._key: tuple[int, str] | None = None

    def acquire(self) -> FolderLock:
        folder = self.folder
        if (blocking := file_in_the_way(folder)) is not None:  # under one: NotADirectoryError
            what = "is a file" if blocking == folder else f"lies under {blocking}, a file"
            raise ValueError(f"{folder} {what}; expected a folder for {self.what}: choose "
                             "another path")
        self.created = not folder.exists()
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / self.name
        key = (os.getpid(), str(path.resolve()))
        if key in _held:  # this process holds it already (a nested call)
            _held[key][1] += 1
            self._key, self.created = key, False
            return self
        for _ in range(20):
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder, what = _holder(fd, self.what)
                os.close(fd)
                raise FolderInUseError(
                    f"{folder} is in use: {holder} is writing {what} there; wait for it "
                    "to finish (or stop it), or choose another folder") from None
            try:  # a run that just ended removed the file we opened: take the new one
                same = os.path.samestat(os.fstat(fd), os.stat(path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        else:  # pragma: no cover
            raise RuntimeError(f"could not lock {path}: it keeps being replaced")
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "command": _command_line(),
                                  "what": self.what}).encode(), 0)
        _held[key] = [fd, 1]
        self._key = key
        if os.environ.get(PAUSE_ENV):  # test hook: two runs started together surely overlap
            time.sleep(float(os.environ[PAUSE_ENV]))
        return self

    def release(self, exc: BaseException | None = None) -> DiskFullError | None:
        """Let go of the lock; returns the one-line error to raise instead of `exc` when it
        is a full disk."""
        key, self._key = self._key, None
        if key is None:
            return None
        fd_depth = _held[key]
        fd_depth[1] -= 1
        if fd_depth[1] == 0:
            del _held[key]
            with contextlib.suppress(OSError):
                os.unlink(key[1])  # while still locked: the next run makes a fresh file
            os.close(fd_depth[0])
            if exc is not None and self.created:
                self._remove_if_unused()
        if exc is None:
            return None
        again = self.again() if callable(self.again) else self.again
        return disk_full_error(exc, self.what, self.folder, again)

    def _remove_if_unused(self) -> None:
        """The run created the folder and failed before writing anything real: remove it."""
        with contextlib.suppress(OSError):
            if not has_content(self.folder, self.stub):
                shutil.rmtree(self.folder)

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, typ: Any, exc: BaseException | None, tb: Any) -> None:
        converted = self.release(exc)
        if converted is not None:
            raise converted from exc


def folder_lock(folder: str | Path, what: str, *, again: Again = "resume",
                name: str = LOCK_FILE, stub: Iterable[str] = ()) -> FolderLock:
    """``with folder_lock(out, "the dataset"):`` write `out` alone (see ``FolderLock``)."""
    return FolderLock(folder, what, again=again, name=name, stub=stub)


def hold_folder(folder: str | Path, what: str, *, again: Again = "resume",
                name: str = LOCK_FILE, stub: Iterable[str] = ()) -> FolderLock:
    """Lock `folder` until the enclosing ``lock_scope`` function returns or raises."""
    held = _scope.get()
    if held is None:
        raise RuntimeError("hold_folder needs a caller decorated with @lock_scope (so the lock "
                           "is released); use `with folder_lock(...)` instead")
    lock = FolderLock(folder, what, again=again, name=name, stub=stub).acquire()
    held.append(lock)
    return lock


def lock_scope[F: Callable[..., Any]](fn: F) -> F:
    """Release the folders `fn` locked with ``hold_folder`` when it returns or raises (a full
    disk raised inside becomes one line naming the folder)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        held: list[FolderLock] = []
        token = _scope.set(held)
        try:
            result = fn(*args, **kwargs)
        except BaseException as exc:
            _scope.reset(token)
            converted = [c for lock in reversed(held) if (c := lock.release(exc)) is not None]
            if converted:  # name the folder on the fullest filesystem
                raise min(converted, key=lambda c: _free(c.folder)) from exc
            raise
        _scope.reset(token)
        for lock in reversed(held):
            lock.release()
        return result

    return wrapper  # type: ignore[return-value]


def _free(folder: Path) -> int:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return 1 << 62
