"""Reading datasets back: frames as a table, stored seeds, and opening one for training.

One opener (``open_lerobot_dataset``) serves the trainer and ``explain``: it checks the folder
is a LeRobotDataset and decodes with PyAV, the decoder the trainer's frame cache uses.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.dataset.robot_episodes import noted_seeds, noted_task
from so101_sim.dataset.store import read_sidecar
from so101_sim.utils.paths import hub_id_hint


class NotADatasetError(ValueError):
    """A folder given as a dataset is not a LeRobotDataset."""


def read_frames(root: Path, columns: list[str]) -> Any:
    """All rows of the dataset's data parquet files (only `columns`), as a pandas DataFrame."""
    import pandas as pd
    import pyarrow.parquet as pq

    files = sorted((root / "data").glob("**/*.parquet"))
    if not files:
        return pd.DataFrame(columns=columns)
    return pd.concat([pq.read_table(f, columns=columns).to_pandas() for f in files],
                     ignore_index=True)


def info_features(root: Path) -> dict[str, Any]:
    """The features in a dataset's meta/info.json ({} before it exists)."""
    path = Path(root) / "meta" / "info.json"
    return json.loads(path.read_text()).get("features", {}) if path.exists() else {}


def stored_seeds(root: str | Path) -> list[int]:
    """Seed of every episode stored in a finalized dataset, in episode order."""
    df = read_frames(Path(root), ["episode_index", "episode_seed"])
    if len(df) == 0:
        return []
    first = df.groupby("episode_index")["episode_seed"].first()
    return [int(np.asarray(v).reshape(-1)[0]) for v in first.sort_index()]


def recorded_task(root: str | Path) -> str | None:
    """The so101-sim task a dataset's episodes ran: from so101-sim record's sidecar, else from
    the sim robot's notes under lerobot-record (None: neither says one task)."""
    task = read_sidecar(Path(root)).get("task")
    return task if isinstance(task, str) else noted_task(Path(root))


def recorded_seeds(root: str | Path) -> list[int] | None:
    """Each episode's reset seed in episode order: the ``episode_seed`` column so101-sim record
    writes, else the sim robot's notes (None: neither)."""
    if "episode_seed" in info_features(Path(root)):
        return stored_seeds(root)
    return noted_seeds(Path(root))


def open_lerobot_dataset(path: str | Path, flag: str = "--dataset",
                         delta_timestamps: dict[str, list[float]] | None = None) -> Any:
    """lerobot's ``LeRobotDataset`` for a local folder (offline), or NotADatasetError."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    path = Path(path)
    if not (path / "meta" / "info.json").is_file():
        raise NotADatasetError(f"{flag} {str(path)!r} is not a LeRobotDataset folder (no "
                               "meta/info.json); record one with `so101-sim record --out DIR`"
                               + hub_id_hint(path, flag, dataset=True))
    # PyAV: the trainer's frame cache decodes with it, so every reader sees the same frames
    try:
        return LeRobotDataset(f"local/{path.name}", root=path,
                              delta_timestamps=delta_timestamps, video_backend="pyav")
    except Exception as exc:  # a torn parquet file, or torn JSON metadata: one line
        if not (isinstance(exc, json.JSONDecodeError)
                or type(exc).__module__.split(".")[0] in ("datasets", "pyarrow")):
            raise
        raise NotADatasetError(_unreadable(path, flag, exc)) from None


def _unreadable(path: Path, flag: str, exc: BaseException) -> str:
    cause = exc.__cause__ or exc  # datasets wraps the parquet reader's error
    return (f"{flag} {str(path)!r} cannot be read as a LeRobotDataset ({type(cause).__name__}: "
            f"{str(cause).splitlines()[0] if str(cause) else cause!r}); a file in it is damaged "
            "(copied in part, or edited): copy or record the dataset again (for a so101-sim "
            "recording, `so101-sim record --out DIR --resume` names the file that changed)")
