"""Decode a LeRobotDataset's camera videos once, resized for the policy, and keep them as arrays.

Decoding mp4 per training sample is what makes CPU training slow; here every video file is
decoded once, a camera's files in parallel threads (a 600-demo recording on a lent GPU
machine's 16 cores: 52 s, against about 250 s one file at a time), each frame goes through
`image_pipeline.resize_frames` (the same resize the harness applies to rendered frames), and the
result is saved as .npy beside the run so a resumed run loads it in seconds.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import av
import numpy as np
from tqdm import tqdm

from so101_sim.utils.image_pipeline import resize_frames

if TYPE_CHECKING:  # annotations only: lerobot loads when a dataset is opened
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

_CHUNK = 256  # frames resized per call


def _decode_file(path: Path, size: tuple[int, int], fps: int) -> dict[int, np.ndarray]:
    """Frame number in the file (round(time * fps)) -> resized uint8 [3, h, w]."""
    frames: dict[int, np.ndarray] = {}
    pending: list[np.ndarray] = []
    numbers: list[int] = []

    def flush() -> None:
        if pending:
            small = resize_frames(np.stack(pending), size).numpy()
            frames.update(zip(numbers, small, strict=True))
            pending.clear()
            numbers.clear()

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        for frame in container.decode(stream):
            numbers.append(round(frame.time * fps))
            pending.append(frame.to_ndarray(format="rgb24"))
            if len(pending) >= _CHUNK:
                flush()
    flush()
    return frames


def decode_camera(dataset: LeRobotDataset, camera_key: str, size: tuple[int, int]) -> np.ndarray:
    """All frames of one camera of `dataset` (a LeRobotDataset) as uint8 [N, 3, h, w]."""
    meta = dataset.meta
    episodes = meta.episodes
    out = np.empty((meta.total_frames, 3, *size), dtype=np.uint8)
    by_file: dict[Path, list[int]] = {}
    for ep in range(meta.total_episodes):
        by_file.setdefault(meta.root / meta.get_video_file_path(ep, camera_key), []).append(ep)
    bar = tqdm(total=meta.total_frames, desc=f"decode {camera_key.split('.')[-1]}", unit="frame",
               leave=False)
    # Decoding and resizing release the GIL, so threads use every core; results stay in order.
    workers = max(1, min(len(by_file), os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        jobs = deque((path, eps, pool.submit(_decode_file, path, size, meta.fps))
                     for path, eps in by_file.items())
        while jobs:
            path, eps, job = jobs.popleft()  # dropping the future frees its frames once copied
            decoded = job.result()
            for ep in eps:
                row = episodes[ep]
                start = round(row[f"videos/{camera_key}/from_timestamp"] * meta.fps)
                lo, hi = row["dataset_from_index"], row["dataset_to_index"]
                for j in range(hi - lo):
                    try:
                        out[lo + j] = decoded[start + j]
                    except KeyError:
                        raise RuntimeError(
                            f"{path}: frame {start + j} (episode {ep}, frame {j}) is missing; "
                            f"the video holds {len(decoded)} frames. The dataset is incomplete: "
                            "re-record it or finish it with `so101-sim record --resume`") from None
                bar.update(hi - lo)
            del decoded, job
    bar.close()
    return out


def _fingerprint(dataset, size: tuple[int, int]) -> str:
    meta = dataset.meta
    info = json.dumps(meta.info, sort_keys=True, default=str)
    key = f"{meta.root.resolve()}|{meta.total_frames}|{size}|{info}"
    return hashlib.sha256(key.encode()).hexdigest()[:16]


def load_frames(dataset: LeRobotDataset, size: tuple[int, int], cache_dir: Path | None
                ) -> dict[str, np.ndarray]:
    """Resized frames for every camera, from `cache_dir` when a matching cache exists."""
    keys = list(dataset.meta.video_keys)
    if not keys:
        raise ValueError(f"dataset {dataset.meta.root} has no video cameras; the policy needs "
                         "observation.images.* recorded as video (so101-sim record does that)")
    fp = _fingerprint(dataset, size)
    frames: dict[str, np.ndarray] = {}
    for key in keys:
        path = cache_dir / f"{key}_{size[0]}x{size[1]}_{fp}.npy" if cache_dir else None
        if path is not None and path.is_file():
            frames[key] = np.load(path)
            continue
        frames[key] = decode_camera(dataset, key, size)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npy")
            np.save(tmp, frames[key])
            tmp.replace(path)
    return frames


def drop_cache(cache_dir: Path) -> int:
    """Delete a finished run's frame cache and say so in one line; returns the bytes freed.

    A six-task cache is ~7 GB and nothing else reads it once the run is done (a later
    `--resume --steps MORE` decodes again, in minutes), so leaving them filled the disk.
    """
    cache_dir = Path(cache_dir)
    if cache_dir.is_symlink() or not cache_dir.is_dir():
        return 0  # shared with another run (benchmarks link one): not ours to delete
    freed = sum(f.stat().st_size for f in cache_dir.rglob("*") if f.is_file())
    shutil.rmtree(cache_dir)
    print(f"so101-sim train: removed the frame cache {cache_dir} ({freed / 1e9:.2f} GB) now that "
          "the run is done; --keep-frame-cache keeps it")
    return freed
