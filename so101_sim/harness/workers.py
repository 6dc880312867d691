"""Env worker processes: one ``PickPlaceEnv`` each, driven by short commands over a pipe.

Why our own pool rather than Gymnasium's ``AsyncVectorEnv``: a worker here runs a whole action
chunk per command and renders only the frames the policy will look at (the last ``n_obs_steps``
of a chunk, or every frame of an episode being filmed), and a worker that dies or hangs is
replaced on its own while the others keep their episodes. ``AsyncVectorEnv`` steps all envs in
lockstep one action at a time, renders every step, and a dead worker breaks the whole vector.

Workers start with ``forkserver`` (never ``fork``: the parent may hold torch's threads) and
create the env, hence their own GL context, after they start.
"""

from __future__ import annotations

import contextlib
import hashlib
import multiprocessing as mp
import os
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any

import numpy as np

from so101_sim.env import CAMERAS
from so101_sim.task import TaskSpec


@dataclass(frozen=True)
class WorkerConfig:
    """What every worker needs to build its env and shape its replies."""

    task: TaskSpec
    render_size: tuple[int, int]
    cameras: tuple[str, ...]  # cameras in the policy's observations
    env_state: bool  # include environment_state in the policy's observations
    n_obs_steps: int


class WorkerDied(RuntimeError):
    """A worker process exited, hung past its timeout, or could not be reached."""


# ------------------------------------------------------------------------ worker side
def _worker_main(conn: Connection, cfg: WorkerConfig) -> None:
    with contextlib.suppress(EOFError, KeyboardInterrupt, BrokenPipeError):
        _serve(conn, cfg)


def _serve(conn: Connection, cfg: WorkerConfig) -> None:
    from so101_sim.env import PickPlaceEnv
    from so101_sim.harness.video import EpisodeVideo

    try:
        env = PickPlaceEnv(task=cfg.task, obs_type="state", image_size=cfg.render_size,
                           render_mode="rgb_array")
    except Exception as exc:
        conn.send(("fatal", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", os.getpid()))
    w = cfg.render_size[1]
    video: EpisodeVideo | None = None
    steps = 0
    digest = hashlib.sha256()

    def observe(with_pixels: bool) -> dict[str, Any]:
        obs: dict[str, Any] = {"agent_pos": env.agent_pos()}
        if cfg.env_state:
            obs["environment_state"] = env.environment_state()
        if with_pixels and cfg.cameras:
            frame = env.render()
            obs["pixels"] = {c: frame[:, i * w:(i + 1) * w] for i, c in enumerate(CAMERAS)
                             if c in cfg.cameras}
        return obs

    while True:
        msg = conn.recv()
        cmd = msg[0]
        if cmd == "close":
            if video is not None:
                video.abort()
            env.close()
            return
        t_phys, t_rend = env.time_physics, env.time_render
        try:
            if cmd == "reset":
                _, seed, video_path = msg
                if video is not None:
                    video.abort()
                    video = None
                env.reset(seed=seed)
                steps = 0
                digest = hashlib.sha256()
                if video_path is not None:
                    video = EpisodeVideo(video_path, env.task.fps, seed)
                    video.add(env.render(), 0)
                reply: dict[str, Any] = {"history": [observe(True)]}
            elif cmd == "act":
                reply = _run_chunk(env, msg[1], cfg.n_obs_steps, observe, video, steps)
                digest.update(np.ascontiguousarray(msg[1][:reply["steps"]], np.float32))
                steps += reply["steps"]
                if reply["done"]:
                    reply["actions_sha"] = digest.hexdigest()[:16]
                if reply["done"] and video is not None:
                    reply["video"] = str(video.finish(reply["outcome"], steps))
                    video = None
            else:
                raise ValueError(f"unknown worker command {cmd!r}")
        except Exception as exc:
            if video is not None:
                video.abort()
                video = None
            conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))
            continue
        reply["physics_s"] = env.time_physics - t_phys
        reply["render_s"] = env.time_render - t_rend
        conn.send(("ok", reply))


def _run_chunk(env: Any, actions: np.ndarray, n_keep: int, observe: Any, video: Any,
               steps_before: int) -> dict[str, Any]:
    """Execute up to len(actions) steps; keep the observations of the last `n_keep` steps."""
    n = len(actions)
    rewards: list[float] = []
    history: list[dict[str, Any]] = []
    done, info = False, {}
    for i, action in enumerate(actions):
        _, reward, terminated, truncated, info = env.step(action)
        rewards.append(float(reward))
        done = terminated or truncated
        if video is not None:
            video.add(env.render(), steps_before + i + 1)
        if done:
            break
        if i >= n - n_keep:
            history.append(observe(True))
    reply: dict[str, Any] = {"steps": len(rewards), "rewards": rewards, "done": done,
                             "history": [] if done else history}
    if done:
        mode = info.get("failure_mode")
        reply["success"] = bool(info.get("is_success", False))
        reply["failure_mode"] = mode
        reply["outcome"] = "success" if mode is None and reply["success"] else (mode or "failed")
    return reply


# ------------------------------------------------------------------------ parent side
class EnvPool:
    """K worker processes; ``send`` a command to some, ``collect`` the replies of all busy ones."""

    def __init__(self, n: int, cfg: WorkerConfig, timeout_s: float = 600.0,
                 start_timeout_s: float = 300.0) -> None:
        self.cfg = cfg
        self.timeout_s = timeout_s
        self.start_timeout_s = start_timeout_s
        self._ctx = mp.get_context("forkserver")
        # The fork server imports the env module once; each worker forks from it ready to go.
        self._ctx.set_forkserver_preload(["so101_sim.env"])
        self._procs: list[Any] = [None] * n
        self._conns: list[Connection | None] = [None] * n
        self._sent_at: dict[int, float] = {}
        for i in range(n):
            self._spawn(i)
        for i in range(n):
            self._await_ready(i)

    @property
    def size(self) -> int:
        return len(self._procs)

    def pid(self, i: int) -> int | None:
        return self._procs[i].pid if self._procs[i] is not None else None

    def _spawn(self, i: int) -> None:
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(target=_worker_main, args=(child, self.cfg),
                                 name=f"so101-eval-worker-{i}", daemon=True)
        proc.start()
        child.close()
        self._procs[i], self._conns[i] = proc, parent

    def _await_ready(self, i: int) -> None:
        conn, proc = self._conns[i], self._procs[i]
        ready = wait([conn, proc.sentinel], timeout=self.start_timeout_s)
        if conn in ready:
            try:
                kind, payload = conn.recv()
            except EOFError:
                kind, payload = "fatal", f"exited with code {proc.exitcode} while starting"
        else:
            kind = "fatal"
            payload = (f"exited with code {proc.exitcode} while starting" if ready else
                       f"not ready after {self.start_timeout_s:.0f} s")
        if kind != "ready":
            self.close()
            raise RuntimeError(f"env worker {i} could not create the env for task "
                               f"{self.cfg.task.name!r} at {self.cfg.render_size}: {payload}")

    def restart(self, i: int) -> None:
        """Replace worker `i` (dead, hung or in an unknown state) with a fresh one."""
        self._kill(i)
        self._spawn(i)
        self._await_ready(i)

    def send(self, i: int, msg: tuple) -> None:
        self._sent_at[i] = time.monotonic()
        with contextlib.suppress(BrokenPipeError, OSError):  # gone: collect() reports it
            self._conns[i].send(msg)

    @property
    def busy(self) -> int:
        """Workers that were sent a command and have not answered yet."""
        return len(self._sent_at)

    def collect(self, wait_all: bool = True) -> dict[int, dict[str, Any] | str | WorkerDied]:
        """Wait for a reply from every worker that was sent a command (``wait_all=False``:
        return as soon as at least one has answered or died).

        Returns, per worker: the reply dict, an error string (the command raised in the worker;
        the worker is still usable), or ``WorkerDied`` (the worker was restarted).
        """
        out: dict[int, dict[str, Any] | str | WorkerDied] = {}
        while self._sent_at and (wait_all or not out):
            by_handle: dict[Any, int] = {}
            for i in self._sent_at:
                by_handle[self._conns[i]] = i
                by_handle[self._procs[i].sentinel] = i
            deadline = min(self._sent_at.values()) + self.timeout_s
            ready = wait(list(by_handle), timeout=max(0.0, deadline - time.monotonic()))
            handled: set[int] = set()
            for h in ready:  # replies first: a worker may exit right after its last reply
                i = by_handle[h]
                if i in handled or h is not self._conns[i]:
                    continue
                handled.add(i)
                try:
                    kind, payload = self._conns[i].recv()
                except (EOFError, OSError):
                    out[i] = self._died(i, "its pipe closed")
                    continue
                del self._sent_at[i]
                out[i] = payload if kind == "ok" else str(payload)
            for h in ready:
                i = by_handle[h]
                if i in handled or i not in self._sent_at:
                    continue
                handled.add(i)
                out[i] = self._died(i, f"it exited with code {self._procs[i].exitcode}")
            now = time.monotonic()
            for i, t in list(self._sent_at.items()):
                if now - t > self.timeout_s:
                    out[i] = self._died(i, f"no reply within {self.timeout_s:.0f} s")
        return out

    def _died(self, i: int, why: str) -> WorkerDied:
        self._sent_at.pop(i, None)
        err = WorkerDied(f"env worker {i} (pid {self.pid(i)}) died: {why}")
        self.restart(i)
        return err

    def _kill(self, i: int) -> None:
        proc, conn = self._procs[i], self._conns[i]
        if conn is not None:
            conn.close()
        if proc is not None:
            if proc.is_alive():
                proc.kill()
            proc.join(timeout=5)
        self._procs[i], self._conns[i] = None, None

    def close(self) -> None:
        for i, conn in enumerate(self._conns):
            if conn is not None and self._procs[i] is not None and self._procs[i].is_alive():
                with contextlib.suppress(BrokenPipeError, OSError):
                    conn.send(("close",))
        for i, proc in enumerate(self._procs):
            if proc is not None:
                proc.join(timeout=5)
            self._kill(i)
        self._sent_at.clear()
