"""The worker side of ``so101-sim eval --save-rollouts``: tape one evaluated episode.

An env worker with a tape renders every step (not only the frames the policy looks at),
feeds both cameras to lerobot's ``StreamingVideoEncoder`` and keeps the low-dimensional
columns. The finished episode comes back with the episode's last reply in the format of a
``record`` worker's result (columns + one mp4 per camera as bytes + video stats), so the
driver spools and writes it with ``so101_sim.dataset.store`` / ``dataset.writer`` and nothing
needs a shared filesystem (local processes and Ray actors alike).
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class TapeSpec:
    """What a worker needs to tape episodes (picklable: it crosses to the worker)."""

    cameras: tuple[str, ...]  # the env's cameras, in render order
    encoder_kwargs: dict[str, Any]  # lerobot RGBEncoderConfig fields
    queue_size: int  # frames the encoder may buffer: a whole episode, so none is dropped

    @property
    def video_keys(self) -> tuple[str, ...]:
        return tuple(f"observation.images.{c}" for c in self.cameras)


class RolloutTape:
    """Collects one episode at a time: ``start``, ``add`` per step, ``finish`` or ``cancel``."""

    def __init__(self, spec: TapeSpec, fps: int) -> None:
        from lerobot.configs.video import RGBEncoderConfig
        from lerobot.datasets.video_utils import StreamingVideoEncoder

        from so101_sim.utils.video_backend import quiet_libav

        quiet_libav()
        self.spec = spec
        self.tmp = Path(tempfile.mkdtemp(prefix="so101-eval-rollout-"))
        self.encoder = StreamingVideoEncoder(
            fps=fps, queue_maxsize=spec.queue_size,
            rgb_encoder=RGBEncoderConfig(**spec.encoder_kwargs), encoder_threads=1)
        self.active = False
        self.seed = 0
        self.cube = np.zeros(3, np.float32)
        self.columns: dict[str, list[Any]] = {}

    def start(self, seed: int, initial_cube_pose: Any) -> None:
        """Begin the episode of `seed` (an unfinished previous one is dropped)."""
        self.cancel()
        self.encoder.start_episode(video_keys=list(self.spec.video_keys), temp_dir=self.tmp)
        self.active = True
        self.seed = int(seed)
        self.cube = np.asarray(initial_cube_pose, dtype=np.float32)
        self.columns = {k: [] for k in ("observation.state", "action", "next.reward",
                                         "next.success", "next.done")}

    def add(self, frame: np.ndarray, state: np.ndarray, executed: np.ndarray, reward: float,
            success: bool, done: bool) -> None:
        """One step: the cameras side by side and the state before it, the action the env
        executed (after its clip), and what the step returned."""
        w = frame.shape[1] // len(self.spec.cameras)
        for i, key in enumerate(self.spec.video_keys):
            self.encoder.feed_frame(key, frame[:, i * w:(i + 1) * w])
        c = self.columns
        c["observation.state"].append(np.asarray(state, dtype=np.float32))
        c["action"].append(np.asarray(executed, dtype=np.float32))
        c["next.reward"].append(np.float32(reward))
        c["next.success"].append(bool(success))
        c["next.done"].append(bool(done))

    def finish(self, success: bool, failure_mode: str | None) -> dict[str, Any]:
        """Close the episode: its columns, mp4 bytes and video stats (``Spool.put``'s input)."""
        videos = self.encoder.finish_episode()
        self.active = False
        out_videos = {}
        for key, (path, stats) in videos.items():
            out_videos[key] = {"mp4": Path(path).read_bytes(), "stats": stats}
            shutil.rmtree(Path(path).parent, ignore_errors=True)
        c, n = self.columns, len(self.columns["action"])
        columns = {
            "observation.state": np.stack(c["observation.state"]),
            "action": np.stack(c["action"]),
            "episode_seed": np.full((n, 1), self.seed, dtype=np.int64),
            "initial_cube_pose": np.repeat(self.cube[None], n, axis=0),
            "next.reward": np.asarray(c["next.reward"], dtype=np.float32).reshape(n, 1),
            "next.success": np.asarray(c["next.success"], dtype=bool).reshape(n, 1),
            "next.done": np.asarray(c["next.done"], dtype=bool).reshape(n, 1),
            "episode_success": np.full((n, 1), bool(success)),
            "episode_failure_mode": np.full(n, failure_mode or ""),
        }
        self.columns = {}
        return {"seed": self.seed, "success": bool(success), "failure_mode": failure_mode,
                "steps": n, "has_data": True, "columns": columns, "videos": out_videos}

    def cancel(self) -> None:
        if self.active:
            self.encoder.cancel_episode()
            self.active = False

    def close(self) -> None:
        self.cancel()
        self.encoder.close()
        shutil.rmtree(self.tmp, ignore_errors=True)
