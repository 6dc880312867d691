"""The episode recorder each `record` worker runs (local process or Ray actor).

A worker simulates, renders and encodes whole episodes: its own env (and GL context, made
after the worker started), scripted expert and lerobot ``StreamingVideoEncoder``. It hands
back the episode's low-dimensional columns and one finished mp4 per camera as bytes, so the
result is the same wherever the worker ran and nothing needs a shared filesystem.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.record.episode import run_episode
from so101_sim.tasks import TaskSpec
from so101_sim.utils.video_backend import quiet_libav


@dataclass(frozen=True)
class RecorderSpec:
    """Everything a recording worker needs (picklable: it crosses to the worker)."""

    task: TaskSpec
    image_size: tuple[int, int]
    dart_noise: float
    expert: dict[str, Any]
    keep_failures: bool
    encoder_kwargs: dict[str, Any]
    queue_size: int  # frames the encoder may buffer: a whole episode, so none is dropped
    temp_dir: str  # used when it exists where the worker runs, else the system's temp

    def __call__(self) -> EpisodeRecorder:
        """Build the recorder (env, GL context, expert, encoder) where this is called."""
        return EpisodeRecorder(self)


class _Columns:
    """`emit` of ``run_episode``: images go to the video encoders, the rest is kept per column."""

    def __init__(self, encoder: Any, video_keys: tuple[str, ...]) -> None:
        self.encoder = encoder
        self.video_keys = video_keys
        self.columns: dict[str, list[np.ndarray]] = {}
        self.time_write = 0.0

    def __call__(self, frame: dict[str, Any]) -> None:
        t = time.perf_counter()
        for key, value in frame.items():
            if key in self.video_keys:
                self.encoder.feed_frame(key, value)
            elif key != "task":
                self.columns.setdefault(key, []).append(value)
        self.time_write += time.perf_counter() - t


class EpisodeRecorder:
    """Records one episode per ``record(seed)`` call."""

    def __init__(self, spec: RecorderSpec) -> None:
        quiet_libav()
        from lerobot.configs.video import RGBEncoderConfig
        from lerobot.datasets.video_utils import StreamingVideoEncoder

        from so101_sim.expert import ScriptedExpert
        from so101_sim.sim import SO101Env as PickPlaceEnv

        self.spec = spec
        base = spec.temp_dir if Path(spec.temp_dir).is_dir() else None
        self.tmp = Path(tempfile.mkdtemp(prefix="worker-", dir=base))
        self.env = PickPlaceEnv(task=spec.task, obs_type="pixels_agent_pos_env_state",
                                image_size=spec.image_size)
        self.video_keys = tuple(f"observation.images.{cam}" for cam in self.env.cameras)
        self.expert = ScriptedExpert(self.env.task, model=self.env.model, **spec.expert)
        self.encoder = StreamingVideoEncoder(
            fps=self.env.task.fps, queue_maxsize=spec.queue_size,
            rgb_encoder=RGBEncoderConfig(**spec.encoder_kwargs), encoder_threads=1)

    def record(self, seed: int) -> dict[str, Any]:
        """Simulate, render and encode the episode of `seed`. A failure the dataset will not
        keep comes back without columns or videos (nothing to send)."""
        env, spec = self.env, self.spec
        phys0, rend0, cpu0 = env.time_physics, env.time_render, time.process_time()
        cols = _Columns(self.encoder, self.video_keys)
        self.encoder.start_episode(video_keys=list(self.video_keys), temp_dir=self.tmp)
        try:
            success, mode, steps = run_episode(env, self.expert, seed, cols, spec.dart_noise)
        except BaseException:
            self.encoder.cancel_episode()
            raise
        t = time.perf_counter()
        videos = self.encoder.finish_episode()  # waits for the encoder threads to drain
        time_write = cols.time_write + time.perf_counter() - t
        keep = success or spec.keep_failures
        out_videos = {}
        for key, (path, stats) in videos.items():
            if keep:
                out_videos[key] = {"mp4": Path(path).read_bytes(), "stats": stats}
            shutil.rmtree(Path(path).parent, ignore_errors=True)
        return {"seed": seed, "success": success, "failure_mode": mode, "steps": steps,
                "has_data": keep,
                "columns": {k: np.stack(v) for k, v in cols.columns.items()} if keep else {},
                "videos": out_videos,
                "time_physics": env.time_physics - phys0, "time_render": env.time_render - rend0,
                "time_write": time_write, "cpu_seconds": time.process_time() - cpu0}

    def close(self) -> None:
        self.encoder.close()
        self.env.close()
        shutil.rmtree(self.tmp, ignore_errors=True)
