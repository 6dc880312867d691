"""Files written whole or not at all, so a reader (or a resume after a kill) never sees half.

Small files (JSON, metadata, reports) are written to a temporary name beside the target,
synced and renamed over it: a kill leaves the old file or the new one. Logs (JSONL) are
appended a whole line at a time and synced; a reader drops a last line that a kill cut short
(``read_jsonl``), and a writer that continues a log cuts it first (``drop_torn_tail``).
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any


def fsync_dir(path: Path) -> None:
    """Make a rename in `path` durable (not every filesystem lets a directory be synced)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def write_atomic(path: str | Path, data: bytes) -> None:
    """Replace `path` with `data` so that a kill leaves the old or the new file, never half.
    A failed write (a full disk) removes its temporary file and leaves the old file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with tmp.open("wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def write_text_atomic(path: str | Path, text: str) -> None:
    """``write_atomic`` for text (UTF-8)."""
    write_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | Path, obj: Any, indent: int | None = 2) -> None:
    """`obj` as JSON (with a final newline), written whole or not at all."""
    write_text_atomic(path, json.dumps(obj, indent=indent) + "\n")


def append_line(path: str | Path, line: str) -> None:
    """Append one line (a newline is added) and sync it: a kill keeps it whole or cuts only
    this last line, which ``read_jsonl`` drops."""
    with Path(path).open("a", encoding="utf-8") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


def drop_torn_tail(path: str | Path) -> bool:
    """Cut a last line that a kill left unfinished (no newline), so the next appended record
    starts on a line of its own. True if something was cut."""
    path = Path(path)
    if not path.is_file():
        return False
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return False
    with path.open("r+b") as f:
        f.truncate(data.rfind(b"\n") + 1)
    return True


def read_jsonl(path: str | Path) -> list[Any]:
    """The records of a JSONL log; a last line a kill cut short (no newline) is dropped.

    A whole line that is not JSON is not something a kill causes (lines are appended whole):
    it raises ValueError naming the file and the line."""
    path = Path(path)
    if not path.is_file():
        return []
    lines = path.read_text(encoding="utf-8", errors="replace").split("\n")
    out = []
    for n, line in enumerate(lines[:-1], 1):  # lines[-1]: "" or the torn tail
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: line {n} is not JSON ({exc.msg}); it was edited or "
                             "corrupted: fix or delete that line") from None
    return out
