"""The dataset side of `so101-sim record`: open (create, or recover and resume), write spooled
episodes through lerobot's own ``add_frame``/``save_episode``, checkpoint.

Everything goes through lerobot's API so the result loads in lerobot unchanged; the one
liberty taken is the video encoder: workers already encoded each episode, so the writer's
streaming encoder is replaced by a stand-in that hands ``save_episode`` those mp4s and their
stats (lerobot 0.6's ``DatasetWriter``). Durability (spool, checkpoints, recovery) is
``so101_sim.dataset.store``'s.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.dataset.reader import info_features, stored_seeds
from so101_sim.dataset.schema import (
    CAMERAS,
    DEFAULT_VCODEC,
    ROBOT_TYPE,
    VCODECS,
    dataset_features,
)
from so101_sim.dataset.store import (
    COMMIT,
    SCRATCH,
    SIDECAR,
    SPOOL,
    RecoveryError,
    checkpoint,
    crash_point,
    read_sidecar,
    recover,
    write_sidecar,
)
from so101_sim.utils.locks import LOCK_FILE, clear_folder, has_content
from so101_sim.utils.versions import installed


class WorkerVideos:
    """Stands in for lerobot's StreamingVideoEncoder inside the writer: ``finish_episode``
    hands ``save_episode`` the episode's pre-encoded mp4s, filed like its own streamed ones."""

    def __init__(self) -> None:
        self.ready: dict[str, tuple[Path, dict | None]] | None = None

    def start_episode(self, *args: Any, **kwargs: Any) -> None:
        pass

    def feed_frame(self, video_key: str, image: Any) -> None:
        pass

    def finish_episode(self) -> dict[str, tuple[Path, dict | None]]:
        if self.ready is None:
            raise RuntimeError("no worker videos queued for this episode")
        crash_point("save_episode")  # the data parquet has the episode, the videos not yet
        ready, self.ready = self.ready, None
        return ready

    def cancel_episode(self) -> None:
        self.ready = None

    def close(self) -> None:
        self.ready = None


def _video_info(features: dict[str, Any]) -> dict[str, Any]:
    """The ``info`` of the first camera ({} before the first episode has videos)."""
    video = next((f for f in features.values() if f.get("dtype") == "video"), {})
    return video.get("info") or {}


def codec_of(features: dict[str, Any]) -> str | None:
    """Codec a dataset's videos were written with (None before the first episode)."""
    info = _video_info(features)
    codec = info.get("video.codec")
    return {"av1": "libsvtav1"}.get(codec, codec)


def encoder_config(vcodec: str, features: dict[str, Any] | None = None) -> Any:
    """lerobot encoder config: the dataset's own settings when it has videos, else ours."""
    from lerobot.configs.video import RGBEncoderConfig

    info = _video_info(features or {})
    if info.get("video.codec"):
        return RGBEncoderConfig.from_video_info(info)
    return RGBEncoderConfig(**VCODECS[vcodec])


def _resume_settings(root: Path, side: dict[str, Any], image_size: tuple[int, int],
                     dart_noise: float, vcodec: str | None, expert: dict[str, Any]) -> str:
    """The codec of the dataset being resumed; refuses settings that differ from its own."""
    if side.get("image_size") and tuple(side["image_size"]) != image_size:
        size = "x".join(str(v) for v in side["image_size"])
        raise ValueError(f"{root} was recorded at {size}, not "
                         f"{image_size[0]}x{image_size[1]}; resume with --image-size {size} "
                         "(a dataset holds one image size)")
    old_noise = float(side.get("dart_noise", 0.0))
    if old_noise != dart_noise:
        raise ValueError(f"{root} was recorded with --dart-noise {old_noise:g}, not "
                         f"{dart_noise:g}; resume with --dart-noise {old_noise:g} (a dataset "
                         "holds one noise level)")
    old_expert = side.get("expert", {})
    if old_expert != expert:
        raise ValueError(f"{root} was recorded with expert options {old_expert}, not {expert}; "
                         "resume with the same --recover / --grasp-clearance")
    codec = side.get("vcodec") or codec_of(info_features(root)) or vcodec or DEFAULT_VCODEC
    if vcodec is not None and vcodec != codec:
        raise ValueError(f"{root} holds {codec} videos; resume with --vcodec {codec} or "
                         "without --vcodec (videos of one dataset share a codec)")
    return codec


def _resumed_cameras(root: Path, asked: tuple[str, ...], given: bool) -> tuple[str, ...]:
    """The cameras of the dataset being resumed (its video keys), or an error if `given`
    cameras differ from them."""
    prefix = "observation.images."
    own = tuple(k[len(prefix):] for k, v in info_features(root).items()
                if k.startswith(prefix) and v.get("dtype") == "video")
    if given and tuple(asked) != own:
        raise ValueError(f"{root} records cameras {','.join(own)}, not {','.join(asked)}; "
                         f"resume with --cameras {','.join(own)} or without --cameras (one "
                         "dataset holds one set of cameras)")
    return own


def _adopt(root: Path, side: dict[str, Any]) -> None:
    """A dataset without a checkpoint: take it as one if it is whole (written before
    checkpoints existed, or killed before its first episode); refuse it otherwise."""
    import pyarrow.parquet as pq

    try:
        info = json.loads((root / "meta" / "info.json").read_text())
        n = int(info["total_episodes"])
        files = sorted((root / "data").glob("**/*.parquet"))
        rows = sum(pq.ParquetFile(f).metadata.num_rows
                   for f in sorted((root / "meta" / "episodes").glob("**/*.parquet")))
        for f in files:
            pq.ParquetFile(f)
        if rows != n or (n == 0 and files):
            raise ValueError(f"info.json says {n} episodes, meta/episodes holds {rows}")
    except (OSError, ValueError, KeyError) as e:
        raise RecoveryError(f"{root} has no checkpoint and is damaged ({e}): it was written by "
                            "an so101-sim without crash recovery and killed; record into a new "
                            "--out") from None
    checkpoint(root, side)


@dataclass
class Opened:
    """A dataset open for appending, and what the recording loop needs to know about it."""

    root: Path
    side: dict[str, Any]
    next_seed: int
    encoder_kwargs: dict[str, Any]
    ds: Any = None
    videos: WorkerVideos | None = None
    repo_id: str = ""
    encoder: Any = None
    queue_size: int = 0

    def reopen(self) -> None:
        """(Re)open the dataset for appending through lerobot's ``resume``."""
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        self.ds = LeRobotDataset.resume(self.repo_id, root=self.root, rgb_encoder=self.encoder,
                                        streaming_encoding=True, encoder_threads=1,
                                        encoder_queue_maxsize=self.queue_size)
        self.videos = _use_worker_videos(self.ds)

    def write(self, entry: dict[str, Any], description: str,
              image_size: tuple[int, int]) -> None:
        """Append one spooled episode through lerobot's add_frame/save_episode."""
        blank = np.zeros((*image_size, 3), dtype=np.uint8)  # shape-checked only
        cols = entry["columns"]
        for i in range(entry["steps"]):
            frame = {k: v[i] for k, v in cols.items()}
            frame["task"] = description
            for key in self.ds.meta.video_keys:
                frame[key] = blank
            self.ds.add_frame(frame)
        ready = {}
        for key, video in entry["videos"].items():  # save_episode moves the file and removes
            tmp = self.root / SCRATCH / f"ep{entry['seed']}-{key}"  # its folder: give a link
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            try:
                os.link(video["path"], tmp / "episode.mp4")
            except OSError:
                shutil.copy2(video["path"], tmp / "episode.mp4")
            ready[key] = (tmp / "episode.mp4", video["stats"])
        self.videos.ready = ready
        with quiet_datasets():
            self.ds.save_episode()

    def checkpoint(self, reopen: bool) -> None:
        """Finalize, record the state as the one a kill comes back to, reopen if asked."""
        if self.ds.has_pending_frames():
            self.ds.clear_episode_buffer()
        self.ds.finalize()
        crash_point("finalize")
        checkpoint(self.root, self.side)
        crash_point("checkpoint")
        if reopen:
            self.reopen()


@contextmanager
def quiet_datasets() -> Iterator[None]:
    """Hide the ``datasets`` "Map:" progress bar save_episode prints per episode, which cut
    through `record`'s own bar (lerobot's loader switches the bars back on whenever it reads
    a parquet file, so per write)."""
    from datasets.utils import logging as ds_logging

    was = ds_logging.is_progress_bar_enabled()
    ds_logging.disable_progress_bar()
    try:
        yield
    finally:
        if was:
            ds_logging.enable_progress_bar()


def _use_worker_videos(ds: Any) -> WorkerVideos:
    """Swap the writer's streaming encoder for `WorkerVideos` (lerobot 0.6 DatasetWriter)."""
    writer = getattr(ds, "writer", None)
    if writer is None or not hasattr(writer, "_streaming_encoder"):
        import lerobot

        raise RuntimeError(f"record relies on lerobot 0.6's DatasetWriter streaming encoder; "
                           f"lerobot {lerobot.__version__} has none: install lerobot==0.6.1")
    old = writer._streaming_encoder
    if old is not None:
        old.close()
    videos = WorkerVideos()
    writer._streaming_encoder = videos
    return videos


def _killed_while_creating(root: Path) -> bool:
    """A folder holding only what a run killed before its dataset existed leaves behind."""
    ours = {"meta", "data", "videos", SIDECAR, COMMIT, SPOOL, SCRATCH, LOCK_FILE}
    return (not (root / "meta" / "info.json").exists()
            and all(p.name in ours for p in root.iterdir())
            and not any(p.is_file() for sub in ("data", "videos") for p in (root / sub).rglob("*")))


def create_dataset(root: Path, **create_kwargs: Any) -> None:
    """``LeRobotDataset.create`` + ``finalize`` into `root`, which exists already (it holds the
    writing run's lock file, and lerobot insists on creating its folder itself): the dataset
    is made in the scratch folder and its folders are moved in."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    stage = root / SCRATCH / "create"
    shutil.rmtree(stage, ignore_errors=True)
    stage.parent.mkdir(parents=True, exist_ok=True)
    ds = LeRobotDataset.create(root=stage, **create_kwargs)
    ds.finalize()
    for sub in sorted(stage.iterdir()):
        sub.rename(root / sub.name)
    shutil.rmtree(root / SCRATCH, ignore_errors=True)


def open_dataset(root: Path, resume: bool, repo_id: str, task_arg: str,
                 image_size: tuple[int, int], seed_start: int, dart_noise: float,
                 vcodec: str | None, queue_size: int, expert: dict[str, Any],
                 cameras: tuple[str, ...] = CAMERAS, cameras_given: bool = False) -> Opened:
    """Create the dataset, or bring it back to its last checkpoint and reopen it; write the
    sidecar. A folder that holds anything needs `resume`; a resumed dataset keeps its own
    cameras (`cameras_given`: the caller asked for `cameras` explicitly, refused if they
    differ)."""
    exists = has_content(root)  # the run's own lock file does not count
    if exists and resume and _killed_while_creating(root):
        clear_folder(root)  # nothing was recorded yet: start as if it had never run
        exists = False
    if exists and not resume:
        if not ((root / "meta" / "info.json").exists() or _killed_while_creating(root)):
            raise ValueError(f"{root} holds other files and no LeRobot dataset (no "
                             "meta/info.json), so --resume cannot continue it either; record "
                             "writes a new dataset into a new or empty folder: choose another "
                             "--out")
        raise ValueError(f"{root} already exists and is not empty; pass --resume to continue "
                         "recording into it, or choose another --out")
    if resume and exists:
        if not (root / "meta" / "info.json").exists():
            raise ValueError(f"{root} is not a LeRobot dataset (no meta/info.json); cannot "
                             "--resume")
        side = read_sidecar(root)
        record = recover(root)
        if record is None:
            _adopt(root, side)
        else:  # seeds tried after the checkpoint are tried again (from the spool, mostly)
            side["tried"], side["failures"] = record["tried"], record["failures"]
        codec = _resume_settings(root, side, image_size, dart_noise, vcodec, expert)
        cameras = _resumed_cameras(root, cameras, cameras_given)
        tried = [int(s) for s in side.get("tried", [])] + stored_seeds(root)
        repo_id = side.get("repo_id", repo_id)
        task_arg = side.get("task", task_arg)
        encoder = encoder_config(codec, info_features(root))
        failures = dict(side.get("failures", {}))
        next_seed = max([seed_start - 1, *tried]) + 1
        fresh = False
        mujoco, now = side.get("mujoco"), installed("mujoco")  # its episodes' MuJoCo, this one
        if mujoco and mujoco != now:
            print(f"so101-sim record: {root} was started with MuJoCo {mujoco} and goes on with "
                  f"{now}: `replay` may not reproduce every episode bit for bit")
    else:
        codec = vcodec or DEFAULT_VCODEC
        encoder = encoder_config(codec)
        root.mkdir(parents=True, exist_ok=True)
        create_dataset(root, repo_id=repo_id, fps=30, robot_type=ROBOT_TYPE,
                       features=dataset_features(image_size, dart_noise > 0, cameras),
                       use_videos=True, rgb_encoder=encoder)
        tried, failures, next_seed, fresh = [], {}, seed_start, True
        mujoco = installed("mujoco")
    side = {"repo_id": repo_id, "task": task_arg, "image_size": list(image_size),
            "dart_noise": dart_noise, "vcodec": codec, "tried": sorted(set(tried)),
            "failures": failures, "expert": expert, "cameras": list(cameras),
            **({"mujoco": mujoco} if mujoco else {})}
    write_sidecar(root, side)
    if fresh:
        checkpoint(root, side)  # the empty dataset: what a kill before any episode returns to
    opened = Opened(root, side, next_seed, dataclasses.asdict(encoder), repo_id=repo_id,
                    encoder=encoder, queue_size=queue_size)
    opened.reopen()
    return opened
