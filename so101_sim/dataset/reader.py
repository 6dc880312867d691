"""Reading datasets back: frames as a table, stored seeds, and opening one for training.

One opener (``open_lerobot_dataset``) serves the trainer and ``explain``: it checks the folder
is a LeRobotDataset and decodes with PyAV, the decoder the trainer's frame cache uses.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


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


def open_lerobot_dataset(path: str | Path, flag: str = "--dataset",
                         delta_timestamps: dict[str, list[float]] | None = None) -> Any:
    """lerobot's ``LeRobotDataset`` for a local folder (offline), or NotADatasetError."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    path = Path(path)
    if not (path / "meta" / "info.json").is_file():
        raise NotADatasetError(f"{flag} {str(path)!r} is not a LeRobotDataset folder (no "
                               "meta/info.json); record one with `so101-sim record --out DIR`")
    # PyAV: the trainer's frame cache decodes with it, so every reader sees the same frames
    return LeRobotDataset(f"local/{path.name}", root=path, delta_timestamps=delta_timestamps,
                          video_backend="pyav")
