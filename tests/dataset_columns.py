"""Read a recorded dataset's parquet columns per episode seed, for tests that compare two
recordings of the same seeds (durability, Ray vs local)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def columns_by_seed(root: Path, columns: tuple[str, ...]) -> dict[int, dict[str, np.ndarray]]:
    """{episode seed: {column: stacked values}} from every data parquet under `root`."""
    import pandas as pd
    import pyarrow.parquet as pq

    df = pd.concat([pq.read_table(f).to_pandas() for f in sorted(root.glob("data/**/*.parquet"))])
    out = {}
    for _, ep in df.sort_values("index").groupby("episode_index"):
        seed = int(np.asarray(ep["episode_seed"].iloc[0]).reshape(-1)[0])
        out[seed] = {c: np.stack([np.asarray(v) for v in ep[c]]) for c in columns}
    return out
