"""The SO-101 task-suite Gymnasium environment (one env class; the task file picks the task)."""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from so101_sim.sim.env_args import (
    check_action,
    check_cameras,
    check_image_size,
    check_mesh_width,
)
from so101_sim.sim.glcheck import mujoco
from so101_sim.sim.rendering import MultiCameraRenderer
from so101_sim.sim.reset_options import Workspace, apply_reset_options, workspace
from so101_sim.sim.scene import SceneIds, build_model, mesh_grid_for
from so101_sim.tasks import DEFAULT_CAMERAS, DEFAULT_TASK, TaskSpec, get_kind, load_task
from so101_sim.tasks.kind import ENV_STATE_BASE
from so101_sim.utils.units import lerobot_to_radians, radians_to_lerobot

OBS_TYPES = ("pixels_agent_pos", "pixels_agent_pos_env_state", "state")
IMAGE_SIZE = (480, 640)  # (height, width) of the demos: the reference dataset's cameras, 640x480
CAMERAS = DEFAULT_CAMERAS  # "wrist" is the third (ALL_CAMERAS)
FAILURE_MODES = get_kind("pick_place").failure_modes
ENV_STATE_SIZE = ENV_STATE_BASE  # pick_place: cube position (3) + quaternion wxyz (4) + goal (3)
_MAX_JOINT_SPEED = 50.0  # rad/s: far beyond the servos (~7 rad/s); only a diverging sim gets here
_MAX_CUBE_SPEED = 20.0  # m/s
_DR_STREAM = 0xD0D0  # second SeedSequence word of the randomization stream (see reset)

# MuJoCo's own "the simulation blew up" warnings: bad qpos/qvel/qacc (it then resets the state
# itself) and bad ctrl.
_INSTABILITY_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL,
                         mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADCTRL)


def _instability_count(d: mujoco.MjData) -> int:
    return sum(int(d.warning[w].number) for w in _INSTABILITY_WARNINGS)


def env_state_size(task: TaskSpec) -> int:
    """Length of ``environment_state``: 10, plus 7 per further cube (stack 17, tidy 24)."""
    return get_kind(task.kind).env_state_size(task)


class SO101Env(gym.Env):
    """SO-101 arm on a table with cubes; the task file says what to do with them.

    Tasks (``envs/*.toml``): ``pick_place`` (red cube onto a green pad), ``pick_place_anywhere``
    (cube and pad anywhere in reach), ``pick_place_dr`` (pick_place with domain
    randomization), ``lift`` (hold the cube 5 cm up for 1 s), ``stack`` (red cube onto a blue
    one), ``tidy`` (three cubes into an open box). ``task.description`` is the instruction
    for language-conditioned policies.

    ## Action space
    ``Box(float32, (6,))``: **absolute joint targets in LeRobot units**, in the order
    ``shoulder_pan, shoulder_lift, elbow_flex, wrist_flex, wrist_roll, gripper``. The five arm
    joints in degrees with 0 at the middle of each joint's range; the gripper 0 (closed) to
    100 (open). Bounds are the joint limits; targets outside them are clipped and counted in
    ``info["action_clipped"]``. Position servos track the targets at ``fps`` Hz control with
    ``physics_substeps`` physics steps per control step (default 30 Hz x 8).

    ## Observation space
    ``obs_type="pixels_agent_pos"`` (default)::

        {"pixels": {camera: uint8[H, W, 3], ...}, "agent_pos": float32[6]}

    with the cameras of ``cameras`` (default the task's, normally ``front`` and ``side``;
    ``wrist`` rides on the gripper). ``"pixels_agent_pos_env_state"`` adds
    ``"environment_state"`` (length ``TaskKind.env_state_size``): float32[10] = first cube's
    position and quaternion (w-x-y-z), goal
    position (target pad; stack: where the red cube's centre belongs; tidy: box centre; lift:
    the point ``lift_height`` above the cube's start), then position+quaternion of every other
    cube (stack: the blue one, 17 in all; tidy: 24). Metres, world frame. ``"state"`` has
    ``agent_pos`` and ``environment_state`` only and never creates a GL context.
    ``agent_pos`` is the measured joint position in the same units as the action.

    ## Reward and episode end
    1 on a step where the task is solved, else 0; ``tidy`` pays the fraction of cubes inside
    the box. Solved (``info["is_success"]``) is the task kind's rule (``so101_sim.tasks``), held
    for ``success.settle_steps`` steps. The episode terminates on success (task option
    ``terminate_on_success``), when the simulation diverges, or truncates at ``max_steps``.
    On the last step ``info["failure_mode"]`` is ``None`` (success) or one of the task's modes
    (``TaskKind.failure_modes``; pick_place: ``"never_grasped"``, ``"dropped"``,
    ``"misplaced"``, ``"timeout"``, ``"sim_unstable"``).

    ## Reset
    The arm starts at the task's rest pose (plus optional uniform noise); objects are placed
    by the task kind (``TaskKind.sample_layout``). With a ``[randomize]`` section, lights,
    colours, table texture, cameras, cube properties, servo gains and distractors are drawn
    too, from a second stream of the same seed (``so101_sim.sim.randomizer``). All randomness
    comes from the reset seed, so a seed and an action sequence fully determine an episode,
    pixels included. ``options`` may pin ``cube_pose=(x, y, yaw_deg)`` (the first cube)
    and/or ``target_pos=(x, y)``.

    ## Arguments
    ``task``: a name in ``envs/`` or a path to a task TOML (or a ``TaskSpec``);
    ``obs_type``: see above; ``image_size``: ``(height, width)`` of each camera;
    ``render_mode``: ``"rgb_array"`` (``render()`` returns the cameras side by side) or None;
    ``cameras``: names from ``("front", "side", "wrist")``, None for the task's;
    ``mesh_width``: the image width whose mesh detail to use (default: ``image_size``'s).

    ## Version history
    v0: first release; the task suite, wrist camera and domain randomization were added
    without changing a ``pick_place`` episode.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, task: str | Path | TaskSpec = DEFAULT_TASK,
                 obs_type: str = "pixels_agent_pos",
                 image_size: tuple[int, int] = IMAGE_SIZE,
                 render_mode: str | None = None,
                 cameras: Sequence[str] | None = None,
                 mesh_width: int | None = None) -> None:
        if obs_type not in OBS_TYPES:
            raise ValueError(f"obs_type={obs_type!r} is invalid; expected one of {OBS_TYPES}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r} is invalid; expected 'rgb_array' "
                             "or None (rendering is headless)")
        self.image_size = check_image_size(image_size)
        self.task = load_task(task)
        self.kind = get_kind(self.task.kind)
        self.cameras = check_cameras(self.task.cameras if cameras is None else cameras)
        self.obs_type = obs_type
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": self.task.fps}

        # Mesh detail follows the image width, or `mesh_width`: a smaller render of a scene
        # recorded at a larger size keeps the geometry the recording (and the policy) saw.
        width = self.image_size[1] if mesh_width is None else check_mesh_width(mesh_width)
        model, self.visuals = build_model(self.task, mesh_grid_for(self.task, width))
        self._randomizer = None
        if self.task.randomize is not None:
            from so101_sim.sim.randomizer import DomainRandomizer

            model = copy.deepcopy(model)  # randomization edits the model: never the shared one
            self._randomizer = DomainRandomizer(model, self.task)
        self.model = model
        self.data = mujoco.MjData(self.model)
        self.ids = SceneIds(self.model, self.task)
        self._ids = self.ids  # older name, kept for existing callers
        self._renderer: MultiCameraRenderer | None = None
        self._frame: np.ndarray | None = None  # last rendered frame, valid until the next step
        self._dr_rng: np.random.Generator | None = None
        self.cube_halves = [s / 2 for s in self._cube_sizes()]

        m = self.model
        lo_rad, hi_rad = m.jnt_range[self.ids.arm_qpos_joints].T
        low = radians_to_lerobot(lo_rad)
        high = radians_to_lerobot(hi_rad)
        low[5], high[5] = 0.0, 100.0
        self.action_low = low.astype(np.float32)
        self.action_high = high.astype(np.float32)
        self.action_space = spaces.Box(self.action_low, self.action_high, dtype=np.float32)
        self.observation_space = self._make_observation_space()

        self._step_count = 0
        self._clipped_total = 0
        self._tracker = self.kind.tracker()
        self._workspace: Workspace | None = None  # table/base bounds for reset options
        self.time_physics = 0.0
        self.time_render = 0.0

    def _cube_sizes(self) -> list[float]:
        return self.kind.cube_sizes(self.task)

    # ---------------------------------------------------------------- spaces and observations
    def _make_observation_space(self) -> spaces.Dict:
        joint_limit = np.float32(360.0)  # measured positions can overshoot limits slightly
        obs: dict[str, spaces.Space] = {
            "agent_pos": spaces.Box(-joint_limit, joint_limit, (6,), np.float32)}
        if self.obs_type != "state":
            h, w = self.image_size
            obs["pixels"] = spaces.Dict(
                {c: spaces.Box(0, 255, (h, w, 3), np.uint8) for c in self.cameras})
        if self.obs_type != "pixels_agent_pos":
            obs["environment_state"] = spaces.Box(-np.inf, np.inf, (env_state_size(self.task),),
                                                  np.float32)
        return spaces.Dict(obs)

    def _get_obs(self) -> dict[str, Any]:
        obs: dict[str, Any] = {"agent_pos": self.agent_pos()}
        if self.obs_type != "state":
            frame = self._render_frame()
            w = self.image_size[1]
            obs["pixels"] = {c: frame[:, i * w:(i + 1) * w].copy()
                             for i, c in enumerate(self.cameras)}
        if self.obs_type != "pixels_agent_pos":
            obs["environment_state"] = self.environment_state()
        return obs

    def agent_pos(self) -> np.ndarray:
        """Measured joint positions in LeRobot units, float32[6]."""
        return radians_to_lerobot(self.data.qpos[self.ids.arm_qpos]).astype(np.float32)

    def environment_state(self) -> np.ndarray:
        """True object poses, float32 (see the class docstring for the layout)."""
        d, q = self.data, self.ids.cubes_qpos
        parts = [d.qpos[q[0]:q[0] + 7], self.goal_pos()] + [d.qpos[a:a + 7] for a in q[1:]]
        return np.concatenate(parts).astype(np.float32)

    def goal_pos(self) -> np.ndarray:
        """Where the (first) cube should go: see ``environment_state`` in the class docstring."""
        return self.kind.goal_pos(self)

    def cube_pos(self, k: int = 0) -> np.ndarray:
        """Position of cube `k` (``TaskKind.cube_names`` order), metres (a view: copy to keep)."""
        a = self.ids.cubes_qpos[k]
        return self.data.qpos[a:a + 3]

    def cube_half(self, k: int = 0) -> float:
        """Half the edge length of cube `k` in this episode (randomized tasks vary it)."""
        return self.cube_halves[k]

    def cube_speed(self, k: int = 0) -> float:
        a = self.ids.cubes_qvel[k]
        return float(np.linalg.norm(self.data.qvel[a:a + 3]))

    def task_state(self) -> dict[str, np.ndarray]:
        """True poses for scripted controllers: cube pos/quat, goal pos, tool-centre point."""
        d, ids = self.data, self.ids
        return {
            "cube_pos": d.qpos[ids.cube_qpos:ids.cube_qpos + 3].copy(),
            "cube_quat": d.qpos[ids.cube_qpos + 3:ids.cube_qpos + 7].copy(),
            "target_pos": np.array(self.goal_pos(), dtype=np.float64),
            "tcp_pos": d.site_xpos[ids.tcp_site].copy(),
            "tcp_xmat": d.site_xmat[ids.tcp_site].reshape(3, 3).copy(),
            "qpos": d.qpos[ids.arm_qpos].copy(),
        }

    # ------------------------------------------------------------------------- rendering
    def _render_frame(self) -> np.ndarray:
        if self._frame is None:
            if self._renderer is None:
                h, w = self.image_size
                self._renderer = MultiCameraRenderer(
                    self.model, self.cameras, h, w, show_collision=self.visuals == "primitive",
                    shadows=self.task.shadows)
            if self._randomizer is not None:
                self._randomizer.upload(self._renderer)
            t0 = time.perf_counter()
            self._frame = self._renderer.render(self.data)
            self.time_render += time.perf_counter() - t0
        return self._frame

    def render(self) -> np.ndarray | None:
        """The cameras side by side, (H, n_cameras * W, 3) uint8 (render_mode="rgb_array")."""
        if self.render_mode != "rgb_array":
            gym.logger.warn("render() needs render_mode='rgb_array'; got None")
            return None
        return self._render_frame().copy()

    # ------------------------------------------------------------------------- reset / step
    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        task, m, d, ids, rng = self.task, self.model, self.data, self.ids, self.np_random
        # Draw every random number in a fixed order, whatever the options, so episodes depend
        # only on the seed.
        noise = rng.uniform(-task.rest_noise, task.rest_noise, size=6)
        layout = self.kind.sample_layout(task, rng)
        if self._workspace is None:
            self._workspace = workspace(m)
        cube, target = apply_reset_options(options, self._workspace, task.cube_size,
                                           layout.cubes[0], layout.target)
        layout.cubes[0] = cube

        mujoco.mj_resetData(m, d)
        if self._randomizer is not None:
            # A stream of its own: pick_place draws exactly what it drew before DR existed.
            if seed is not None or self._dr_rng is None:
                self._dr_rng = np.random.default_rng(None if seed is None else [seed, _DR_STREAM])
            sizes = self._randomizer.apply(self._dr_rng, d, layout.cubes, target)
            self.cube_halves = [s / 2 for s in sizes]
        rest = np.clip(np.asarray(task.rest_pose) + noise, self.action_low, self.action_high)
        q = lerobot_to_radians(rest)
        d.qpos[ids.arm_qpos] = q
        d.ctrl[:] = q
        for k, (adr, pose) in enumerate(zip(ids.cubes_qpos, layout.cubes, strict=True)):
            yaw = np.deg2rad(pose[2])
            d.qpos[adr:adr + 7] = [pose[0], pose[1], self.cube_halves[k],
                                   np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        goal_z = self.kind.goal_height(task, self.cube_halves[0])
        d.mocap_pos[ids.target_mocap] = [target[0], target[1], goal_z]
        mujoco.mj_forward(m, d)

        self._step_count = 0
        self._clipped_total = 0
        self._tracker = self.kind.tracker()
        self._frame = None
        self.initial_cube_pose = cube.copy()
        self.initial_target_pos = target.copy()
        info = {"is_success": False, "cube_pose": cube.copy(), "target_pos": target.copy()}
        return self._get_obs(), info

    def validate_action(self, action: Any) -> np.ndarray:
        """Return `action` as float64[6] or raise ValueError saying what was expected."""
        return check_action(action)

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        a = self.validate_action(action)  # raises before any state changes
        clipped = np.clip(a, self.action_low, self.action_high)
        n_clipped = int(np.count_nonzero(clipped != a))
        self._clipped_total += n_clipped

        m, d = self.model, self.data
        t0 = time.perf_counter()
        d.ctrl[:] = lerobot_to_radians(clipped)
        bad_before = _instability_count(d)
        mujoco.mj_step(m, d, nstep=self.task.physics_substeps)
        unstable = _instability_count(d) > bad_before or not self._state_is_sane()
        self.time_physics += time.perf_counter() - t0
        self._frame = None
        self._step_count += 1

        if unstable:
            # MuJoCo may have reset the state itself; restore something finite to observe.
            mujoco.mj_resetData(m, d)
            mujoco.mj_forward(m, d)
            success, reward = False, 0.0
        else:
            success, reward = self._tracker.update(self, clipped)
        terminated = unstable or (success and self.task.terminate_on_success)
        truncated = not terminated and self._step_count >= self.task.max_steps
        info: dict[str, Any] = {
            "is_success": success,
            "action_clipped": n_clipped,
            "action_clipped_total": self._clipped_total,
        }
        if terminated or truncated:
            info["failure_mode"] = ("sim_unstable" if unstable
                                    else None if success else self._tracker.failure_mode(self))
        return self._get_obs(), reward, terminated, truncated, info

    def _state_is_sane(self) -> bool:
        d, ids = self.data, self.ids
        if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))):
            return False
        cube_speed = max(self.cube_speed(k) for k in range(len(ids.cubes_qvel)))
        return (np.max(np.abs(d.qvel[ids.arm_qvel])) < _MAX_JOINT_SPEED
                and cube_speed < _MAX_CUBE_SPEED)

    # ---------------------------------------------------------------- contact helpers
    def cube_contacts(self, k: int = 0) -> tuple[bool, bool, bool]:
        """For cube `k`: (fixed pad touches it, moving pad touches it, any robot geom does)."""
        d, ids = self.data, self.ids
        geom = ids.cube_geoms[k]
        fixed = moving = robot = False
        for i in range(d.ncon):
            c = d.contact[i]
            g1, g2 = c.geom1, c.geom2
            if geom not in (g1, g2):
                continue
            other = g2 if g1 == geom else g1
            if other in ids.robot_geoms:
                robot = True
                fixed |= other == ids.fixed_pad
                moving |= other == ids.moving_pad
        return fixed, moving, robot

    def pad_clearance(self, k: int = 0) -> float:
        """Smallest distance between cube `k` and either finger pad (m), capped at 5 cm."""
        m, d, ids = self.model, self.data, self.ids
        return min(mujoco.mj_geomDistance(m, d, ids.cube_geoms[k], pad, 0.05, None)
                   for pad in (ids.fixed_pad, ids.moving_pad))

    def __getstate__(self) -> dict[str, Any]:
        """Copies and pickles leave the renderer behind (a GL context cannot be copied); the
        copy makes its own at its first frame, with the same pixels."""
        return {**self.__dict__, "_renderer": None}

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


#: The registered env's class; the name predates the other tasks.
PickPlaceEnv = SO101Env
