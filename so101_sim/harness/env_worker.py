"""The env that evaluation runs in each worker (local process or Ray actor).

A worker runs a whole action chunk per call and renders only the frames the policy will look
at (the last ``n_obs_steps`` of a chunk, or every frame of an episode being filmed). A filmed
episode is encoded inside the worker and comes back as mp4 bytes with the episode's last
reply, so the driver writes every file itself, wherever the worker ran. With a ``TapeSpec``
(``eval --save-rollouts``) every step is rendered and taped (``rollout_tape``); the episode
comes back as ``rollout`` in its last reply. Without one the loop is unchanged.
"""

from __future__ import annotations

import hashlib
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from so101_sim.harness.rollout_tape import TapeSpec
from so101_sim.tasks import TaskSpec


@dataclass(frozen=True)
class EnvWorkerConfig:
    """What every worker needs to build its env and shape its replies (picklable)."""

    task: TaskSpec
    render_size: tuple[int, int]
    cameras: tuple[str, ...]  # cameras in the policy's observations
    env_state: bool  # include environment_state in the policy's observations
    n_obs_steps: int
    rollout: TapeSpec | None = None  # tape every episode (eval --save-rollouts)
    mesh_width: int | None = None  # mesh detail of this image width (default render width)
    # Resize the policy's frames here, to this (h, w), with the training resize: a reply then
    # carries 60x80 frames instead of 240x320 ones, small enough for the pipe's buffer, so a
    # worker never blocks on a driver busy in a forward, and the resizes run in parallel.
    resize_to: tuple[int, int] | None = None

    def __call__(self) -> EnvWorker:
        """Build the worker's env (and its GL context) where this is called."""
        return EnvWorker(self)


class EnvWorker:
    """One ``PickPlaceEnv`` driven by ``reset`` and ``act`` calls."""

    def __init__(self, cfg: EnvWorkerConfig) -> None:
        from so101_sim.sim import SO101Env as PickPlaceEnv

        self.cfg = cfg
        self.env = PickPlaceEnv(task=cfg.task, obs_type="state", image_size=cfg.render_size,
                                render_mode="rgb_array", mesh_width=cfg.mesh_width)
        self.video: Any = None
        self.steps = 0
        self.digest = hashlib.sha256()
        self._tmp: Path | None = None  # made when the first filmed episode starts
        self.tape: Any = None
        self._resize: Any = None
        if cfg.resize_to is not None:
            import torch

            from so101_sim.utils.image_pipeline import resize_pixels

            torch.set_num_threads(1)  # one worker, one core: no OpenMP pool spinning in each
            self._resize = resize_pixels
        if cfg.rollout is not None:
            from so101_sim.harness.rollout_tape import RolloutTape

            self.tape = RolloutTape(cfg.rollout, cfg.task.fps)

    def _observe(self, with_pixels: bool) -> dict[str, Any]:
        env, cfg = self.env, self.cfg
        obs: dict[str, Any] = {"agent_pos": env.agent_pos()}
        if cfg.env_state:
            obs["environment_state"] = env.environment_state()
        if with_pixels and cfg.cameras:
            w = cfg.render_size[1]
            frame = env.render()
            obs["pixels"] = {c: frame[:, i * w:(i + 1) * w] for i, c in enumerate(env.cameras)
                             if c in cfg.cameras}
            if self._resize is not None:
                obs["pixels"] = self._resize(obs["pixels"], cfg.resize_to)
        return obs

    def _timed(self, fn: Any, *args: Any) -> dict[str, Any]:
        t_phys, t_rend = self.env.time_physics, self.env.time_render
        try:
            reply = fn(*args)
        except BaseException:
            self._drop_video()
            if self.tape is not None:
                self.tape.cancel()
            raise
        reply["physics_s"] = self.env.time_physics - t_phys
        reply["render_s"] = self.env.time_render - t_rend
        return reply

    def reset(self, seed: int, film: bool = False) -> dict[str, Any]:
        """Start the episode of `seed` (filmed if `film`); reply with its first observation."""
        return self._timed(self._reset, seed, film)

    def _reset(self, seed: int, film: bool) -> dict[str, Any]:
        self._drop_video()
        self.env.reset(seed=seed)
        self.steps = 0
        self.digest = hashlib.sha256()
        if self.tape is not None:
            self.tape.start(seed, self.env.initial_cube_pose)
        if film:  # imported here: a run without videos never loads cv2 and imageio
            from so101_sim.harness.video import EpisodeVideo

            if self._tmp is None:
                self._tmp = Path(tempfile.mkdtemp(prefix="so101-eval-video-"))
            self.video = EpisodeVideo(self._tmp / f"seed{seed}.mp4", self.env.task.fps, seed)
            self.video.add(self.env.render(), 0)
        return {"history": [self._observe(True)]}

    def act(self, actions: np.ndarray) -> dict[str, Any]:
        """Execute up to ``len(actions)`` steps; keep the observations of the last
        ``n_obs_steps``. At the episode's end the reply has its outcome, the digest of the
        executed actions and, if filmed, ``video_mp4`` (bytes)."""
        return self._timed(self._act, actions)

    def _act(self, actions: np.ndarray) -> dict[str, Any]:
        env, n, n_keep, tape = self.env, len(actions), self.cfg.n_obs_steps, self.tape
        rewards: list[float] = []
        history: list[dict[str, Any]] = []
        done, info = False, {}
        for i, action in enumerate(actions):
            if tape is not None:  # the frame and state this step starts from
                frame, state = env.render(), env.agent_pos()
            _, reward, terminated, truncated, info = env.step(action)
            rewards.append(float(reward))
            done = terminated or truncated
            if tape is not None:  # the env clips targets to the joint limits: store that
                executed = np.clip(np.asarray(action, np.float64), env.action_low,
                                   env.action_high)
                tape.add(frame, state, executed, reward, info.get("is_success", False), done)
            if self.video is not None:
                self.video.add(env.render(), self.steps + i + 1)
            if done:
                break
            if i >= n - n_keep:
                history.append(self._observe(True))
        self.digest.update(np.ascontiguousarray(actions[:len(rewards)], np.float32))
        self.steps += len(rewards)
        reply: dict[str, Any] = {"steps": len(rewards), "rewards": rewards, "done": done,
                                 "history": [] if done else history}
        if done:
            mode = info.get("failure_mode")
            reply["success"] = bool(info.get("is_success", False))
            reply["failure_mode"] = mode
            reply["outcome"] = ("success" if mode is None and reply["success"]
                                else (mode or "failed"))
            reply["actions_sha"] = self.digest.hexdigest()[:16]
            if tape is not None:
                reply["rollout"] = tape.finish(reply["success"], mode)
            if self.video is not None:
                path = self.video.finish(reply["outcome"], self.steps)
                self.video = None
                reply["video_mp4"] = path.read_bytes()
                path.unlink()
        return reply

    def _drop_video(self) -> None:
        if self.video is not None:
            self.video.abort()
            self.video = None

    def close(self) -> None:
        self._drop_video()
        if self.tape is not None:
            self.tape.close()
        self.env.close()
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
