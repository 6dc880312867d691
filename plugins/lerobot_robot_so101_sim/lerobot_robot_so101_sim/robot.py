"""The so101-sim arm as a ``lerobot.robots.Robot``: so101_follower's features, simulated.

One sim episode per seed (``seed``, ``seed + 1``, ...): ``connect`` starts the first, every
``send_action`` is one control step of the env (``SO101Env``, 30 Hz), and an episode ends when
the env terminates (success, an unstable simulation) or truncates (the task's ``max_steps``).
Then the robot appends the outcome to ``outcomes`` and logs it, and either starts the next seed
at once or holds the last frame (``episode_end``, see ``SO101SimConfig``): while lerobot records
the episode into a dataset the scene holds until lerobot saves that dataset episode, so each
dataset episode is exactly one sim episode, from its reset, whatever the machine's speed. A
recorded episode that lerobot stops recording first (its ``episode_time_s`` ran out) ends as
``unfinished``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from lerobot.robots.robot import Robot
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from lerobot_robot_so101_sim import registry
from lerobot_robot_so101_sim.config import ROBOT_TYPE, SO101SimConfig
from lerobot_robot_so101_sim.dataset_events import (
    note_saved_episode,
    unwatch_datasets,
    watch_datasets,
)
from so101_sim.policy_frames import refuse_or_warn, robot_input_problem, size_warning
from so101_sim.tasks import load_task
from so101_sim.utils.lerobot_cli import config_errors
from so101_sim.utils.text import counted
from so101_sim.utils.units import FEATURE_NAMES

logger = logging.getLogger(__name__)


@dataclass
class _Episode:
    """One sim episode: its seed and what lerobot did with it."""

    index: int
    seed: int
    steps: int = 0
    frames: int = 0  # dataset frames recorded while it ran (add_frame calls)
    success: bool = False  # the env's is_success after the last step
    over: bool = False
    outcome: dict[str, Any] = field(default_factory=dict)
    written: bool = False  # outcome appended to outcomes_path


class SO101Sim(Robot):
    """``--robot.type=so101_sim``: the MuJoCo SO-101 of so101-sim behind lerobot's Robot API.

    Action and joint features are so101_follower's (``shoulder_pan.pos`` ... ``gripper.pos``:
    degrees with 0 at mid-range, gripper 0..100), so a real so101_leader or a script written
    for the real arm drives it unchanged; observations add the task's cameras by name.
    ``outcomes`` lists one dict per ended episode (episode, seed, success, failure_mode,
    steps, recorded_frames, ended_by, dataset_episode, discarded).
    """

    config_class = SO101SimConfig
    name = ROBOT_TYPE

    def __init__(self, config: SO101SimConfig) -> None:
        super().__init__(config)
        self.config = config
        self.task = load_task(config.task)  # the config has checked it and the cameras
        self.camera_names = names = tuple(config.camera_names) or tuple(self.task.cameras)
        # lerobot sizes its image writers with len(robot.cameras): name -> (H, W, 3)
        self.cameras = {c: (*config.image_size, 3) for c in names}
        self.outcomes: list[dict[str, Any]] = []
        self._env: Any = None
        self._lock = threading.RLock()
        self._episode: _Episode | None = None
        self._started = 0  # episodes started since construction
        self._ended = 0  # episodes ended and not discarded (for config.episodes)
        self._next_seed = config.seed
        self._target = np.zeros(6, dtype=np.float32)  # the joint targets being held
        self._deadline: float | None = None  # realtime: earliest time of the next step
        self._obs: tuple[tuple[int, int], dict[str, Any]] | None = None  # per (episode, step)
        self._stop = "no"  # --robot.episodes: "no", "asked" (stop at the next call), "sent"

    def __str__(self) -> str:
        return f"so101_sim robot {self.id!r}" if self.id else "so101_sim robot"

    # ------------------------------------------------------------------ features
    @property
    def _motors_ft(self) -> dict[str, type]:
        return dict.fromkeys(FEATURE_NAMES, float)

    @property
    def observation_features(self) -> dict[str, type | tuple]:
        return {**self._motors_ft, **self.cameras}

    @property
    def action_features(self) -> dict[str, type]:
        return self._motors_ft

    # ------------------------------------------------------------------ connection
    @property
    def is_connected(self) -> bool:
        return self._env is not None

    @property
    def is_calibrated(self) -> bool:
        return True

    def connect(self, calibrate: bool = True) -> None:
        """Build the scene (the GL context comes with the first frame) and start the first
        episode; a simulated arm needs no calibration, so `calibrate` changes nothing."""
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        self._check_inputs()
        if self.camera_names:  # a GL backend that cannot work: one line, before the scene
            from so101_sim.sim.rendering import select_gl_backend

            with config_errors(f"--robot.type={ROBOT_TYPE}", (RuntimeError,)):
                select_gl_backend()
        registry.add(self)
        try:
            from so101_sim.sim import SO101Env

            cfg = self.config
            self._env = SO101Env(self.task, obs_type="state", image_size=cfg.render_size,
                                 render_mode="rgb_array", cameras=self.camera_names,
                                 mesh_width=cfg.mesh_width or None)
            self.configure()
            watch_datasets(self)
            with self._lock:
                self._start_episode(self._next_seed)
        except BaseException:
            self._release()
            raise
        logger.info("%s connected: task %s, cameras %s at %dx%d%s, %s", self, self.task.name,
                    ",".join(self.camera_names), *cfg.image_size, cfg.connect_note(),
                    "realtime" if cfg.realtime else "not paced (realtime=false)")
        warning = size_warning(sys.argv, self.config.image_size, self.camera_names)
        if warning:  # the policy was built apart from the robot: its frames would be wrong
            logger.warning("%s: %s", self, warning)

    def _check_inputs(self) -> None:
        """Refuse (or warn, for a policy type that does without) a policy on the command line
        that reads an input this robot does not send, before the scene is built."""
        def warn(text: str) -> None:
            logger.warning("%s: %s", self, text)

        refuse_or_warn(robot_input_problem(sys.argv, self.camera_names,
                                           self.config.patched_server),
                       f"--robot.type={ROBOT_TYPE}", warn)

    def calibrate(self) -> None:
        """Nothing to calibrate: the sim's joints are LeRobot's units by construction."""

    def configure(self) -> None:
        """Nothing to configure: servo gains and limits come from the task's MJCF."""

    def disconnect(self) -> None:
        """End a running episode (``ended_by: disconnect``), write what is pending and free the
        GL context."""
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected; call connect() first")
        with self._lock:
            ep = self._episode
            if ep is not None and not ep.over and ep.steps > 0:
                self._end_episode(ep, "disconnect", start_next=False)
            if ep is not None and ep.over:
                self._settle(ep)
            self._release()
        done = [o for o in self.outcomes if not o["discarded"] and o["ended_by"] != "disconnect"]
        wins = sum(o["success"] for o in done)
        share = f" ({100 * wins / len(done):.0f}%)" if done else ""
        logger.info("%s disconnected: %s ended, %d succeeded%s", self,
                    counted(len(done), "episode"), wins, share)

    def _release(self) -> None:
        unwatch_datasets(self)
        registry.remove(self)
        if self._env is not None:
            self._env.close()
            self._env = None

    # ------------------------------------------------------------------ observations, actions
    def get_observation(self) -> dict[str, Any]:
        """Joint positions (LeRobot units) and one (H, W, 3) uint8 image per camera."""
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected; call connect() first")
        with self._lock:
            ep = self._episode
            key = (ep.index, ep.steps)
            if self._obs is None or self._obs[0] != key:
                self._obs = (key, self._observe())
            return dict(self._obs[1])  # callers add keys (robot_client adds "task")

    def _observe(self) -> dict[str, Any]:
        env, cfg = self._env, self.config
        obs: dict[str, Any] = dict(zip(FEATURE_NAMES, map(float, env.agent_pos()), strict=True))
        frame = env.render()  # the cameras side by side
        w = cfg.render_size[1]
        shots = [frame[:, i * w:(i + 1) * w] for i in range(len(self.camera_names))]
        if cfg.render_size != cfg.image_size:
            from so101_sim.utils.image_pipeline import resize_frames

            small = resize_frames(np.stack(shots), cfg.image_size)
            shots = list(small.permute(0, 2, 3, 1).contiguous().numpy())
        else:
            shots = [np.ascontiguousarray(s) for s in shots]
        obs.update(zip(self.camera_names, shots, strict=True))
        return obs

    def send_action(self, action: dict[str, Any]) -> dict[str, float]:
        """One control step towards `action`'s joint targets; returns the targets applied
        (clipped to the joint limits). Joints left out keep their last target, as on the real
        follower. After the episode's end the arm holds and actions are ignored."""
        if not self.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected; call connect() first")
        with self._lock:
            target = self._parse_action(action)
            self._pace()
            ep = self._episode
            if not ep.over and ep.frames and ep.frames < ep.steps:
                # The last step was not recorded: lerobot's recording of this episode is over.
                self._end_episode(ep, "lerobot")
            ep = self._episode
            if not ep.over:
                env = self._env
                target = np.clip(target, env.action_low, env.action_high)
                _, _, terminated, truncated, info = env.step(target)
                self._target = target
                ep.steps += 1
                ep.success = bool(info["is_success"])
                if terminated or truncated:
                    self._end_episode(ep, "env", info.get("failure_mode"))
            applied = dict(zip(FEATURE_NAMES, map(float, self._target), strict=True))
        self._maybe_stop()
        return applied

    def _parse_action(self, action: dict[str, Any]) -> np.ndarray:
        unknown = [k for k in action if k not in FEATURE_NAMES]
        if unknown:
            raise ValueError(f"send_action got {unknown}; expected keys among "
                             f"{list(FEATURE_NAMES)} (so101_follower's action features)")
        target = self._target.copy()
        for i, key in enumerate(FEATURE_NAMES):
            if key in action:
                try:
                    value = float(action[key])
                except (TypeError, ValueError) as exc:
                    raise ValueError(f"send_action: {key}={action[key]!r} is not a number; "
                                     "expected degrees (gripper 0..100)") from exc
                if not math.isfinite(value):
                    raise ValueError(f"send_action: {key}={value} is not finite; expected "
                                     "degrees (gripper 0..100)")
                target[i] = value
        return target

    def _pace(self) -> None:
        """realtime: at most one step per control period (1/fps), as the real arm moves."""
        if not self.config.realtime:
            return
        now = time.perf_counter()
        if self._deadline is not None and now < self._deadline:
            time.sleep(self._deadline - now)
            now = self._deadline
        self._deadline = now + 1.0 / self.task.fps

    # ------------------------------------------------------------------ episodes
    def _start_episode(self, seed: int) -> None:
        obs, _ = self._env.reset(seed=seed)
        self._episode = _Episode(index=self._started, seed=seed)
        self._started += 1
        self._next_seed = seed + 1
        self._target = np.asarray(obs["agent_pos"], dtype=np.float32).copy()
        self._obs = None

    def _end_episode(self, ep: _Episode, ended_by: str, failure_mode: str | None = None,
                     start_next: bool = True) -> None:
        ep.over = True
        if ended_by != "env":
            failure_mode = None if ep.success else "unfinished"
        ep.outcome = {"episode": ep.index, "seed": ep.seed, "task": self.task.name,
                      "success": ep.success, "failure_mode": failure_mode, "steps": ep.steps,
                      "recorded_frames": ep.frames, "ended_by": ended_by,
                      "dataset_episode": None, "discarded": False}
        self.outcomes.append(ep.outcome)
        self._ended += 1
        result = "success" if ep.success else f"failure ({failure_mode})"
        if ended_by == "disconnect" and not ep.success:
            result = "unfinished at disconnect"
        note = ""
        if ended_by == "lerobot" and not ep.success:
            note = (f": lerobot stopped recording it first; raise --dataset.episode_time_s (the "
                    f"task runs up to {self.task.max_steps} steps, "
                    f"{self.task.max_steps / self.task.fps:.0f} s at {self.task.fps} Hz)")
        logger.info("so101_sim episode %d (seed %d): %s after %d steps%s", ep.index, ep.seed,
                    result, ep.steps, note)
        if not start_next:
            return
        mode = self.config.episode_end
        if mode == "hold" or (mode == "auto" and ep.frames):
            until = ("lerobot saves or discards its dataset episode" if ep.frames
                     else "a dataset episode ends (episode_end=hold)")
            logger.info("so101_sim: holding the last frame until %s", until)
            return
        self._settle(ep)
        self._start_episode(self._next_seed)
        self._check_count()

    def on_dataset_event(self, event: str, dataset: Any) -> None:
        """lerobot recorded a frame, saved or discarded a dataset episode (``dataset_events``)."""
        with self._lock:
            ep = self._episode
            if ep is None or not self.is_connected:
                return
            if event == "frame":
                ep.frames += 1
                return
            if self.config.episode_end == "reset" or (not ep.frames and not ep.over):
                return  # this sim episode is no part of that dataset episode
            if not ep.over:
                self._end_episode(ep, "lerobot", start_next=False)
            if event == "saved":
                ep.outcome["dataset_episode"] = int(dataset.num_episodes) - 1 if ep.frames else None
                seed = self._next_seed
            else:  # discarded: the same scene again, as a person would set it up again
                ep.outcome["discarded"] = True
                self._ended -= 1
                seed = ep.seed
                logger.info("so101_sim: dataset episode discarded; seed %d runs again", seed)
            self._settle(ep)
            if event == "saved":
                note_saved_episode(dataset, ep.outcome)
            self._start_episode(seed)
            self._check_count()
        self._maybe_stop()

    def _check_count(self) -> None:
        """Called once an ended episode is settled (the next one started)."""
        if self.config.episodes and self._ended >= self.config.episodes and self._stop == "no":
            self._stop = "asked"

    def _maybe_stop(self) -> None:
        """--robot.episodes reached: stop the command as Ctrl-C does (lerobot-rollout shuts down
        gracefully, lerobot-teleoperate and robot_client stop on KeyboardInterrupt); once."""
        if self._stop == "asked":
            self._stop = "sent"
            logger.info("so101_sim: %s ended (--robot.episodes=%d): stopping as Ctrl-C would",
                        counted(self._ended, "episode"), self.config.episodes)
            os.kill(os.getpid(), signal.SIGINT)

    def _settle(self, ep: _Episode) -> None:
        """The episode is behind us: complete its outcome and append it to outcomes_path."""
        if ep.written or not ep.outcome:
            return
        ep.written = True
        ep.outcome["recorded_frames"] = ep.frames  # the held frames after its end included
        path = self.config.outcomes_path
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "a", encoding="utf-8") as f:
                f.write(json.dumps(ep.outcome) + "\n")

    # ------------------------------------------------------------------ for the expert
    @property
    def env(self) -> Any:
        """The ``SO101Env`` being simulated (None while disconnected)."""
        return self._env

    @property
    def episode(self) -> tuple[int, int, int, bool]:
        """(index, seed, steps taken, over) of the current episode."""
        ep = self._episode
        if ep is None:
            raise DeviceNotConnectedError(f"{self} is not connected; call connect() first")
        return ep.index, ep.seed, ep.steps, ep.over

    def state_observation(self) -> dict[str, np.ndarray]:
        """``agent_pos`` and ``environment_state`` of the current state: what the scripted
        expert reads (true object poses, never shown to a policy)."""
        with self._lock:
            if self._env is None:
                raise DeviceNotConnectedError(f"{self} is not connected; call connect() first")
            return {"agent_pos": self._env.agent_pos(),
                    "environment_state": self._env.environment_state()}

    def held_action(self) -> dict[str, float]:
        """The joint targets being held (after an episode's end: where the arm stays)."""
        return dict(zip(FEATURE_NAMES, map(float, self._target), strict=True))
