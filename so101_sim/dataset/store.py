"""What makes `so101-sim record` survive a hard kill (SIGKILL, OOM, power loss).

lerobot writes a dataset in place: the current session's data parquet has no footer until
``finalize``, episode metadata waits in memory, ``info.json`` and ``stats.json`` are rewritten
per episode. A kill mid-session leaves files that do not load. Three pieces fix that:

- The **spool** (``.so101_spool/<seed>/``): a finished episode is written there first, whole or
  not at all (temporary name, fsync, rename), before it goes into the dataset: its columns,
  its encoded videos with their stats, its outcome.
- **Checkpoints** (``.so101_commit.json``, one atomic file): every N episodes and at the end
  the dataset is finalized and its state recorded: the size of every file, the bytes of the
  small files lerobot rewrites in place (``meta/info.json``, ``stats.json``, ``tasks.parquet``)
  and the sidecar's tried seeds. Spool entries of checkpointed episodes are dropped after it.
- **Recovery** (``--resume``): files the checkpoint does not list are deleted and the rewritten
  ones restored, so the dataset is exactly the checkpoint again; temporary folders are removed.
  Episodes after the checkpoint come back from the spool without simulating, and an episode
  that was still running is simulated again from its seed (episodes are deterministic).

This relies on lerobot 0.6 never changing a finalized data, video or episode-metadata file when
a resumed writer appends (it starts new files); recovery checks the sizes and refuses if not.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import signal
import tempfile
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.utils.atomic import fsync_dir as _fsync_dir
from so101_sim.utils.atomic import write_atomic

SIDECAR = "so101_sim_recording.json"
SPOOL = ".so101_spool"
SCRATCH = ".so101_tmp"  # temporary files of this run (lerobot's too): same filesystem
COMMIT = ".so101_commit.json"
DATASET_DIRS = ("data", "meta", "videos")
CRASH_ENV = "SO101_SIM_CRASH_AT"  # test hook: "point:n" SIGKILLs at the n-th pass of point
_passes: Counter[str] = Counter()


class RecoveryError(ValueError):
    """The dataset cannot be brought back to a checkpoint."""


def crash_point(name: str) -> None:
    """Test hook: SIGKILL this process the n-th time it reaches `name` when the environment
    has ``SO101_SIM_CRASH_AT=name:n``; the kill tests use it to hit exact moments."""
    want = os.environ.get(CRASH_ENV)
    if not want:
        return
    point, _, nth = want.partition(":")
    if point == name:
        _passes[name] += 1
        if _passes[name] == int(nth or 1):
            os.kill(os.getpid(), signal.SIGKILL)


# ----------------------------------------------------------------------------- small files
# write_atomic lives in utils.atomic (other layers use it too); importable from here as before.


def read_sidecar(root: Path) -> dict[str, Any]:
    """The recording's settings and tried seeds ({} for a folder without one)."""
    path = Path(root) / SIDECAR
    if not path.exists():
        return {}
    try:
        return json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is corrupt ({e}); it is not something a kill can cause "
                         "(it is replaced atomically): restore it, or record into a new --out"
                         ) from None


def write_sidecar(root: Path, data: dict[str, Any]) -> None:
    write_atomic(Path(root) / SIDECAR, json.dumps(data, indent=1).encode())


@contextlib.contextmanager
def scratch(root: Path) -> Iterator[Path]:
    """A temporary folder inside the dataset, also used by ``tempfile`` (lerobot's video
    concatenation) while recording: moves stay renames, and a kill leaves nothing elsewhere."""
    import multiprocessing.util

    multiprocessing.util.get_temp_dir()  # multiprocessing's own (sockets) stays where it was
    path = Path(root) / SCRATCH
    path.mkdir(exist_ok=True)
    old, tempfile.tempdir = tempfile.tempdir, str(path)
    try:
        yield path
    finally:
        tempfile.tempdir = old


# ----------------------------------------------------------------------------- spool
class Spool:
    """Finished episodes not yet in a checkpoint: one folder per seed, complete or absent."""

    def __init__(self, root: Path) -> None:
        self.dir = Path(root) / SPOOL

    def put(self, result: dict[str, Any]) -> None:
        """Store a worker's episode result (columns, ``videos`` as mp4 bytes + stats)."""
        seed = int(result["seed"])
        part = self.dir / f"{seed}.part"
        shutil.rmtree(part, ignore_errors=True)
        part.mkdir(parents=True)
        files = []
        meta = {k: v for k, v in result.items() if k not in ("columns", "videos")}
        meta["videos"] = sorted(result.get("videos", {}))
        if result.get("columns"):
            np.savez(part / "columns.npz", **result["columns"])
            files.append(part / "columns.npz")
            stats = {f"{key}|{name}": value for key, video in result["videos"].items()
                     for name, value in (video["stats"] or {}).items()}
            np.savez(part / "stats.npz", **stats)
            files.append(part / "stats.npz")
            for key, video in result["videos"].items():
                (part / f"{key}.mp4").write_bytes(video["mp4"])
                files.append(part / f"{key}.mp4")
        (part / "episode.json").write_text(json.dumps(meta))
        files.append(part / "episode.json")
        for f in files:
            with f.open("rb") as fh:
                os.fsync(fh.fileno())
        _fsync_dir(part)
        final = self.dir / str(seed)
        shutil.rmtree(final, ignore_errors=True)
        part.rename(final)
        _fsync_dir(self.dir)

    def meta(self, seed: int) -> dict[str, Any] | None:
        """Outcome and timings of a spooled episode, or None when it is not spooled."""
        path = self.dir / str(seed) / "episode.json"
        return json.loads(path.read_text()) if path.exists() else None

    def load(self, seed: int) -> dict[str, Any]:
        """The whole episode: ``columns`` arrays and ``videos`` {key: {path, stats}}."""
        d = self.dir / str(seed)
        entry = json.loads((d / "episode.json").read_text())
        with np.load(d / "columns.npz") as cols:
            entry["columns"] = {k: cols[k] for k in cols.files}
        with np.load(d / "stats.npz") as st:
            stats: dict[str, dict[str, np.ndarray]] = {}
            for k in st.files:
                key, name = k.split("|")
                stats.setdefault(key, {})[name] = st[k]
        entry["videos"] = {key: {"path": d / f"{key}.mp4", "stats": stats.get(key)}
                           for key in entry["videos"]}
        return entry

    def seeds(self) -> list[int]:
        if not self.dir.exists():
            return []
        return sorted(int(p.name) for p in self.dir.iterdir() if p.name.isdigit())

    def drop(self, seeds: Iterable[int]) -> None:
        for seed in seeds:
            shutil.rmtree(self.dir / str(seed), ignore_errors=True)

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


# ----------------------------------------------------------------------------- checkpoints
def _dataset_files(root: Path) -> Iterator[tuple[str, Path]]:
    for sub in DATASET_DIRS:
        for path in sorted((root / sub).rglob("*")):
            if path.is_file():
                yield path.relative_to(root).as_posix(), path


def checkpoint(root: Path, side: dict[str, Any]) -> None:
    """Record the finalized dataset at `root` (and the sidecar's seeds) as the state to come
    back to. Call only right after ``finalize``: then every file is complete."""
    files, saved = {}, {}
    for rel, path in _dataset_files(root):
        files[rel] = path.stat().st_size
        if path.parent == root / "meta":  # rewritten in place by a resumed writer
            saved[rel] = base64.b64encode(path.read_bytes()).decode()
    record = {"version": 1, "files": files, "saved": saved, "tried": side.get("tried", []),
              "failures": side.get("failures", {})}
    write_atomic(root / COMMIT, json.dumps(record).encode())


def recover(root: Path) -> dict[str, Any] | None:
    """Bring the dataset at `root` back to its last checkpoint and remove temporary files.

    Returns the checkpoint record, or None for a dataset without one (written before
    checkpoints existed, or killed before its first).
    """
    root = Path(root)
    shutil.rmtree(root / SCRATCH, ignore_errors=True)
    for p in root.glob("tmp*"):  # lerobot's streaming-encoder folders, older versions' too
        if p.is_dir() and all(f.suffix == ".mp4" for f in p.rglob("*") if f.is_file()):
            shutil.rmtree(p, ignore_errors=True)
    for name in (SIDECAR, COMMIT):
        (root / f"{name}.tmp").unlink(missing_ok=True)
    for p in (root / SPOOL).glob("*.part"):
        shutil.rmtree(p, ignore_errors=True)
    path = root / COMMIT
    if not path.exists():
        return None
    record = json.loads(path.read_text())
    listed: dict[str, int] = record["files"]
    for rel, p in list(_dataset_files(root)):
        if rel not in listed:
            p.unlink()
    for rel, b64 in record["saved"].items():
        data = base64.b64decode(b64)
        p = root / rel
        if not p.exists() or p.read_bytes() != data:
            p.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(p, data)
    for rel, size in listed.items():
        p = root / rel
        have = p.stat().st_size if p.exists() else None
        if have != size:
            raise RecoveryError(
                f"cannot bring {root} back to its last checkpoint: {rel} is "
                f"{'missing' if have is None else f'{have} bytes'}, expected {size} bytes; "
                "a finalized file was changed or removed after the checkpoint. Record into a "
                "new --out (or restore that file)")
    for sub in DATASET_DIRS:  # folders emptied by the deletions above
        for d in sorted((root / sub).rglob("*"), key=lambda q: -len(q.parts)):
            if d.is_dir() and not any(d.iterdir()):
                d.rmdir()
    return record
