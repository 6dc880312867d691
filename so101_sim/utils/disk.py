"""A full disk is one line: what was being written, the space left there, and how to go on.

ENOSPC surfaces from many places (our own writes, PyAV's encoder, lerobot's video
concatenation, torch.save) and often wrapped in another exception; ``is_disk_full`` looks
through the whole chain. Finished work is never lost to it (episodes are spooled, files are
written whole or not at all), so the message ends with the command that continues the run.
"""

from __future__ import annotations

import errno
import shlex
import shutil
from pathlib import Path

_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT}
_FULL_TEXT = ("No space left on device", "Disk quota exceeded")
_command: list[str] | None = None


def set_command(argv: list[str] | None) -> None:
    """Remember the command line being run (the CLI calls it, and clears it with None when the
    command returns), so a disk-full message can print the exact command that continues it."""
    global _command
    _command = None if argv is None else list(argv)


def is_disk_full(exc: BaseException | None) -> bool:
    """Whether `exc`, or any exception it was raised from or during, is a full disk."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, DiskFullError):
            return True
        if isinstance(exc, OSError) and exc.errno in _FULL_ERRNOS:
            return True
        if any(t in str(exc) for t in _FULL_TEXT):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def free_space(path: str | Path) -> str:
    """Free space on the filesystem of `path` (or of its nearest existing parent), readable."""
    p = Path(path).expanduser().absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        free = float(shutil.disk_usage(p).free)
    except OSError:
        return "unknown space"
    for unit in ("B", "KB", "MB", "GB"):
        if free < 1024 or unit == "GB":
            return f"{free:.0f} {unit}" if unit == "B" else f"{free:.1f} {unit}"
        free /= 1024
    return f"{free:.1f} TB"  # pragma: no cover


def note_default_out(folder: str | Path) -> None:
    """The registered command ran without --out and writes `folder`: the command that
    continues it must name that folder, or it would start another new one."""
    global _command
    if _command is not None and "--out" not in _command:
        _command = [*_command, "--out", str(folder)]


def resume_command() -> str | None:
    """The registered command with --resume (and its --out), or None outside the CLI."""
    if _command is None:
        return None
    return shlex.join(_command if "--resume" in _command else [*_command, "--resume"])


def again_hint(again: str) -> str:
    """How to continue after freeing space: the exact command when the CLI registered it."""
    if again == "resume":
        command = resume_command()
        if command is None:
            return "free some space, then run the same command with --resume"
        return f"free some space, then run: {command}"
    if _command is None:
        return "free some space, then run the same command again"
    return f"free some space, then run again: {shlex.join(_command)}"


class DiskFullError(RuntimeError):
    """The disk filled up while a command wrote `folder`; the message is one line."""

    def __init__(self, what: str, folder: str | Path, again: str = "resume",
                 file: str | None = None) -> None:
        self.folder = Path(folder)
        where = f" ({file})" if file else ""
        super().__init__(f"the disk is full: writing {what} {folder}{where} failed with 'No "
                         f"space left on device' ({free_space(folder)} free there); nothing "
                         "finished is lost: "
                         f"{again_hint(again)}")


def disk_full_error(exc: BaseException, what: str, folder: str | Path,
                    again: str = "resume") -> DiskFullError | None:
    """A one-line DiskFullError for `exc` if it is a full disk (else None); an existing one
    (raised for an inner folder) is kept as it is."""
    if isinstance(exc, DiskFullError) or not is_disk_full(exc):
        return None
    return DiskFullError(what, folder, again, getattr(exc, "filename", None))
