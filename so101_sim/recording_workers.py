"""Parallel recording: worker processes that simulate, render and encode whole episodes.

Used by `so101_sim.recording.record` when `workers > 1`; see that module's docstring for the
design (one writer, worker mp4s standing in for lerobot's streaming encoder, seeds in order).
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import shutil
import signal
import time
import traceback
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.recording import (
    VIDEO_KEYS,
    WORKER_TMP,
    _close,
    _Interrupts,
    _Opened,
    _quiet_libav,
    _Tally,
    check_seed_range,
    run_episode,
)


@dataclass(frozen=True)
class _WorkerSpec:
    """Everything a worker process needs (picklable: it crosses to the worker process)."""

    task: str
    image_size: tuple[int, int]
    dart_noise: float
    expert: dict[str, Any]
    keep_failures: bool
    encoder_kwargs: dict[str, Any]
    queue_size: int
    temp_dir: str


class _WorkerVideos:
    """Stands in for lerobot's StreamingVideoEncoder inside the parent's DatasetWriter.

    The worker already encoded the episode; ``finish_episode`` hands the writer those mp4s and
    their stats, so ``save_episode`` files them exactly as it files its own streamed videos.
    """

    def __init__(self) -> None:
        self.ready: dict[str, tuple[Path, dict | None]] | None = None

    def start_episode(self, *args: Any, **kwargs: Any) -> None:
        pass

    def feed_frame(self, video_key: str, image: Any) -> None:
        pass

    def finish_episode(self) -> dict[str, tuple[Path, dict | None]]:
        if self.ready is None:
            raise RuntimeError("no worker videos queued for this episode")
        ready, self.ready = self.ready, None
        return ready

    def cancel_episode(self) -> None:
        self.ready = None

    def close(self) -> None:
        self.ready = None


def _use_worker_videos(ds: Any) -> _WorkerVideos:
    """Swap the writer's streaming encoder for `_WorkerVideos` (lerobot 0.6 DatasetWriter)."""
    writer = getattr(ds, "writer", None)
    if writer is None or not hasattr(writer, "_streaming_encoder"):
        import lerobot

        raise RuntimeError(f"--workers > 1 relies on lerobot 0.6's DatasetWriter streaming "
                           f"encoder; lerobot {lerobot.__version__} has none: use --workers 1")
    old = writer._streaming_encoder
    if old is not None:
        old.close()
    videos = _WorkerVideos()
    writer._streaming_encoder = videos
    return videos


class _EpisodeColumns:
    """Worker side of `emit`: images go to the video encoders, the rest is kept per column."""

    def __init__(self, encoder: Any, temp_dir: Path) -> None:
        self.encoder = encoder
        self.columns: dict[str, list[np.ndarray]] = {}
        self.time_write = 0.0
        encoder.start_episode(video_keys=list(VIDEO_KEYS), temp_dir=temp_dir)

    def __call__(self, frame: dict[str, Any]) -> None:
        t = time.perf_counter()
        for key, value in frame.items():
            if key in VIDEO_KEYS:
                self.encoder.feed_frame(key, value)
            elif key != "task":
                self.columns.setdefault(key, []).append(value)
        self.time_write += time.perf_counter() - t


def _worker_episode(env: Any, expert: Any, encoder: Any, spec: _WorkerSpec,
                    seed: int) -> dict[str, Any]:
    """Record one episode in a worker; the result is small (columns and two mp4 paths)."""
    phys0, rend0, cpu0 = env.time_physics, env.time_render, time.process_time()
    cols = _EpisodeColumns(encoder, Path(spec.temp_dir))
    success, mode, steps = run_episode(env, expert, seed, cols, spec.dart_noise)
    t = time.perf_counter()
    videos = encoder.finish_episode()  # waits for the encoder threads to drain the queue
    time_write = cols.time_write + time.perf_counter() - t
    keep = success or spec.keep_failures
    if not keep:
        for path, _ in videos.values():
            shutil.rmtree(path.parent, ignore_errors=True)
    return {"seed": seed, "success": success, "failure_mode": mode, "steps": steps,
            "keep": keep,
            "columns": {k: np.stack(v) for k, v in cols.columns.items()} if keep else {},
            "videos": {k: (str(p), s) for k, (p, s) in videos.items()} if keep else {},
            "time_physics": env.time_physics - phys0, "time_render": env.time_render - rend0,
            "time_write": time_write, "cpu_seconds": time.process_time() - cpu0}


def _next_seed(tasks: Any) -> int | None:
    """Block for the next seed; None when told to stop or when the parent has died."""
    parent = mp.parent_process()
    while True:
        try:
            return tasks.get(timeout=1.0)
        except queue.Empty:
            if parent is not None and not parent.is_alive():
                return None



def _worker_main(spec: _WorkerSpec, tasks: Any, results: Any) -> None:
    """Worker process: take seeds, record episodes, send results; the parent handles signals."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole process group
    _quiet_libav()
    from lerobot.configs.video import RGBEncoderConfig
    from lerobot.datasets.video_utils import StreamingVideoEncoder

    from so101_sim.env import PickPlaceEnv
    from so101_sim.expert import ScriptedExpert

    seed = None
    try:
        env = PickPlaceEnv(task=spec.task, obs_type="pixels_agent_pos_env_state",
                           image_size=spec.image_size)
        expert = ScriptedExpert(env.task, **spec.expert)
        encoder = StreamingVideoEncoder(fps=env.task.fps, queue_maxsize=spec.queue_size,
                                        rgb_encoder=RGBEncoderConfig(**spec.encoder_kwargs),
                                        encoder_threads=1)
        while (seed := _next_seed(tasks)) is not None:
            results.put(("ok", _worker_episode(env, expert, encoder, spec, seed)))
    except Exception:
        results.put(("error", seed, traceback.format_exc()))
    parent = mp.parent_process()
    if parent is not None and not parent.is_alive():
        results.cancel_join_thread()  # nobody reads our last result: do not hang on exit


@dataclass
class _Dispatcher:
    """Hands out seeds in increasing order and writes results back in that order.

    A seed goes out only while ``kept + in flight < wanted``: even if every episode in flight
    succeeds, nothing surplus is recorded, so the kept seeds equal a one-process run's.
    """

    next_seed: int
    window: int  # at most this many seeds running or queued (each worker busy + one queued)
    in_flight: list[int] = field(default_factory=list)  # dispatched, in order, not yet written
    done: dict[int, dict[str, Any]] = field(default_factory=dict)  # arrived, not yet written

    def to_send(self, kept: int, wanted: int) -> list[int]:
        will_keep = kept + sum(r["keep"] for r in self.done.values())
        pending = len(self.in_flight) - len(self.done)
        seeds = []
        while pending < self.window and will_keep + pending < wanted:
            check_seed_range(self.next_seed)
            seeds.append(self.next_seed)
            self.in_flight.append(self.next_seed)
            self.next_seed += 1
            pending += 1
        return seeds

    def arrived(self, result: dict[str, Any]) -> None:
        self.done[result["seed"]] = result

    def ready(self) -> Iterator[dict[str, Any]]:
        """Arrived results whose lower seeds are all written, lowest first."""
        while self.in_flight and self.in_flight[0] in self.done:
            yield self.done.pop(self.in_flight.pop(0))

    def leftovers(self) -> list[dict[str, Any]]:
        """On an early stop: the completed episodes still waiting for a lower seed."""
        out = [self.done.pop(s) for s in sorted(self.done)]
        self.in_flight.clear()
        return out


def _save_result(ds: Any, videos: _WorkerVideos, result: dict[str, Any], description: str,
                 blank: np.ndarray) -> None:
    """Write one worker episode through lerobot's add_frame/save_episode (videos pre-encoded)."""
    cols = result["columns"]
    for i in range(result["steps"]):
        frame = {k: v[i] for k, v in cols.items()}
        frame["task"] = description
        for key in VIDEO_KEYS:
            frame[key] = blank  # validated for shape only; the pixels are in the worker's mp4
        ds.add_frame(frame)
    videos.ready = {k: (Path(p), s) for k, (p, s) in result["videos"].items()}
    ds.save_episode()


def _receive(results: Any, procs: list[Any]) -> dict[str, Any]:
    """Next worker result; raises if a worker failed or died."""
    while True:
        try:
            msg = results.get(timeout=1.0)
        except queue.Empty:
            dead = [p for p in procs if not p.is_alive()]
            if dead:
                raise RuntimeError(f"recording worker pid {dead[0].pid} exited with code "
                                   f"{dead[0].exitcode} before finishing its episode") from None
            continue
        if msg[0] == "error":
            raise RuntimeError(f"recording worker failed on seed {msg[1]}:\n{msg[2]}")
        return msg[1]


def _stop_workers(procs: list[Any], tasks: Any, results: Any, graceful: bool) -> None:
    """Let idle workers exit; kill busy ones (an interrupted episode is dropped anyway)."""
    if graceful:
        for _ in procs:
            tasks.put(None)
        for p in procs:
            p.join(timeout=10)
    else:
        for q in (tasks, results):
            q.cancel_join_thread()  # never block our exit on a pipe nobody reads
    for p in procs:
        if p.is_alive():
            p.terminate()
            p.join(timeout=10)


def _worker_context() -> Any:
    """Forkserver: workers start clean (no inherited threads or GL context, unlike fork) but
    share one preloaded import of lerobot/torch (~5 CPU-s each with spawn)."""
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["so101_sim.recording_workers", "lerobot.datasets.video_utils",
                                "so101_sim.env", "so101_sim.expert"])
    return ctx


def record_with_workers(opened: _Opened, tally: _Tally, keep_failures: bool,
                         image_size: tuple[int, int], workers: int, task: Any) -> None:
    """W processes simulate/render/encode; this one writes their episodes in seed order."""
    ds, side, root = opened.ds, opened.side, tally.root
    videos = _use_worker_videos(ds)
    temp_dir = root / WORKER_TMP
    shutil.rmtree(temp_dir, ignore_errors=True)  # leftovers of a killed run
    temp_dir.mkdir()
    spec = _WorkerSpec(side["task"], image_size, side["dart_noise"], side["expert"], keep_failures,
                       opened.encoder_kwargs, task.max_steps + 2, str(temp_dir))
    description = task.description
    blank = np.zeros((*image_size, 3), dtype=np.uint8)
    ctx = _worker_context()
    tasks, results = ctx.Queue(), ctx.Queue()
    procs = [ctx.Process(target=_worker_main, args=(spec, tasks, results), daemon=True)
             for _ in range(workers)]
    dispatch = _Dispatcher(opened.next_seed, window=2 * workers)
    cpu0, finished = time.process_time(), False
    interrupts = _Interrupts()
    interrupts.install()

    def write(result: dict[str, Any]) -> None:
        with interrupts.deferred():
            t = time.perf_counter()
            if result["keep"]:
                _save_result(ds, videos, result, description, blank)
            for key in ("time_physics", "time_render", "time_write", "cpu_seconds"):
                setattr(tally, key, getattr(tally, key) + result[key])
            tally.time_write += time.perf_counter() - t
            tally.episode(result["seed"], result["success"], result["failure_mode"],
                          result["steps"], result["keep"])
        tally.show()

    try:
        for p in procs:
            p.start()
        while True:
            for seed in dispatch.to_send(tally.kept, tally.n_episodes):
                tasks.put(seed)
            if not dispatch.in_flight:
                break
            dispatch.arrived(_receive(results, procs))
            for result in dispatch.ready():
                write(result)
        finished = True
    finally:
        interrupts.ignore()
        try:
            _stop_workers(procs, tasks, results, graceful=finished)
            for result in dispatch.leftovers():
                write(result)
            tally.cpu_seconds += time.process_time() - cpu0
            _close(ds, tally)
            shutil.rmtree(temp_dir, ignore_errors=True)
        finally:
            interrupts.restore()
