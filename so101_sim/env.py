"""The SO-101 pick-and-place Gymnasium environment."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from so101_sim.glcheck import mujoco
from so101_sim.rendering import MultiCameraRenderer
from so101_sim.reset_options import Workspace, apply_reset_options, workspace
from so101_sim.scene import build_model, mesh_grid_for
from so101_sim.task import TaskSpec, load_task
from so101_sim.units import MOTOR_NAMES, lerobot_to_radians, radians_to_lerobot

OBS_TYPES = ("pixels_agent_pos", "pixels_agent_pos_env_state", "state")
CAMERAS = ("front", "side")
FAILURE_MODES = ("never_grasped", "dropped", "misplaced", "timeout", "sim_unstable")
ENV_STATE_SIZE = 10  # cube position (3) + cube quaternion wxyz (4) + target position (3)
_MAX_JOINT_SPEED = 50.0  # rad/s: far beyond the servos (~7 rad/s); only a diverging sim gets here
_MAX_CUBE_SPEED = 20.0  # m/s


# MuJoCo's own "the simulation blew up" warnings: bad qpos/qvel/qacc (it then resets the state
# itself) and bad ctrl.
_INSTABILITY_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL,
                         mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADCTRL)


def _instability_count(d: mujoco.MjData) -> int:
    return sum(int(d.warning[w].number) for w in _INSTABILITY_WARNINGS)


class PickPlaceEnv(gym.Env):
    """SO-101 arm picks a red cube and places it on a green target pad.

    ## Action space
    ``Box(float32, (6,))``: **absolute joint targets in LeRobot units**, in the order
    ``shoulder_pan, shoulder_lift, elbow_flex, wrist_flex, wrist_roll, gripper``. The five arm
    joints in degrees with 0 at the middle of each joint's range; the gripper 0 (closed) to
    100 (open). Bounds are the joint limits; targets outside them are clipped and counted in
    ``info["action_clipped"]``. Position servos track the targets at ``fps`` Hz control with
    ``physics_substeps`` physics steps per control step (default 30 Hz x 8).

    ## Observation space
    ``obs_type="pixels_agent_pos"`` (default)::

        {"pixels": {"front": uint8[H, W, 3], "side": uint8[H, W, 3]}, "agent_pos": float32[6]}

    ``"pixels_agent_pos_env_state"`` adds ``"environment_state": float32[10]`` (cube position,
    cube quaternion w-x-y-z, target position; metres, world frame). ``"state"`` has
    ``agent_pos`` and ``environment_state`` only and never creates a GL context.
    ``agent_pos`` is the measured joint position in the same units as the action.

    ## Reward and episode end
    Sparse: 1 on a step where the task is solved, else 0. Solved (``info["is_success"]``) means
    the cube rests inside the target radius, no finger touches it, and it has stayed that way
    for ``success.settle_steps`` steps. The episode terminates on success (task option
    ``terminate_on_success``), when the simulation diverges, or truncates at ``max_steps``.
    On the last step ``info["failure_mode"]`` is one of ``None`` (success), ``"never_grasped"``,
    ``"dropped"``, ``"misplaced"``, ``"timeout"`` or ``"sim_unstable"``.

    ## Reset
    The arm starts at the task's rest pose (plus optional uniform noise); the cube's x, y and
    yaw and the target's x, y are drawn from the task's ranges. All randomness comes from the
    reset seed, so a seed and an action sequence fully determine an episode. ``options`` may
    pin ``cube_pose=(x, y, yaw_deg)`` and/or ``target_pos=(x, y)``.

    ## Arguments
    ``task``: a name in ``envs/`` or a path to a task TOML (or a ``TaskSpec``);
    ``obs_type``: see above; ``image_size``: ``(height, width)`` of each camera;
    ``render_mode``: ``"rgb_array"`` (``render()`` returns front|side side by side) or None.

    ## Version history
    v0: first release.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, task: str | Path | TaskSpec = "pick_place",
                 obs_type: str = "pixels_agent_pos",
                 image_size: tuple[int, int] = (480, 640),
                 render_mode: str | None = None) -> None:
        if obs_type not in OBS_TYPES:
            raise ValueError(f"obs_type={obs_type!r} is invalid; expected one of {OBS_TYPES}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r} is invalid; expected 'rgb_array' "
                             "or None (rendering is headless)")
        self.image_size = _check_image_size(image_size)
        self.task = load_task(task)
        self.obs_type = obs_type
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": self.task.fps}

        self.model, self.visuals = build_model(
            self.task, mesh_grid_for(self.task, self.image_size[1]))
        self.data = mujoco.MjData(self.model)
        self._ids = _SceneIds(self.model)
        self._renderer: MultiCameraRenderer | None = None
        self._frame: np.ndarray | None = None  # last rendered front|side, valid for _frame_step

        m = self.model
        lo_rad, hi_rad = m.jnt_range[self._ids.arm_qpos_joints].T
        low = radians_to_lerobot(lo_rad)
        high = radians_to_lerobot(hi_rad)
        low[5], high[5] = 0.0, 100.0
        self.action_low = low.astype(np.float32)
        self.action_high = high.astype(np.float32)
        self.action_space = spaces.Box(self.action_low, self.action_high, dtype=np.float32)
        self.observation_space = self._make_observation_space()

        self._step_count = 0
        self._clipped_total = 0
        self._tracker = _OutcomeTracker()
        self._workspace: Workspace | None = None  # table/base bounds for reset options
        self.time_physics = 0.0
        self.time_render = 0.0

    # ---------------------------------------------------------------- spaces and observations
    def _make_observation_space(self) -> spaces.Dict:
        joint_limit = np.float32(360.0)  # measured positions can overshoot limits slightly
        obs: dict[str, spaces.Space] = {
            "agent_pos": spaces.Box(-joint_limit, joint_limit, (6,), np.float32)}
        if self.obs_type != "state":
            h, w = self.image_size
            obs["pixels"] = spaces.Dict(
                {c: spaces.Box(0, 255, (h, w, 3), np.uint8) for c in CAMERAS})
        if self.obs_type != "pixels_agent_pos":
            obs["environment_state"] = spaces.Box(-np.inf, np.inf, (ENV_STATE_SIZE,), np.float32)
        return spaces.Dict(obs)

    def _get_obs(self) -> dict[str, Any]:
        obs: dict[str, Any] = {"agent_pos": self.agent_pos()}
        if self.obs_type != "state":
            frame = self._render_frame()
            w = self.image_size[1]
            obs["pixels"] = {c: frame[:, i * w:(i + 1) * w].copy() for i, c in enumerate(CAMERAS)}
        if self.obs_type != "pixels_agent_pos":
            obs["environment_state"] = self.environment_state()
        return obs

    def agent_pos(self) -> np.ndarray:
        """Measured joint positions in LeRobot units, float32[6]."""
        return radians_to_lerobot(self.data.qpos[self._ids.arm_qpos]).astype(np.float32)

    def environment_state(self) -> np.ndarray:
        d, ids = self.data, self._ids
        return np.concatenate([d.qpos[ids.cube_qpos:ids.cube_qpos + 7],
                               d.mocap_pos[ids.target_mocap]]).astype(np.float32)

    def task_state(self) -> dict[str, np.ndarray]:
        """True poses for scripted controllers: cube pos/quat, target pos, tool-centre point."""
        d, ids = self.data, self._ids
        return {
            "cube_pos": d.qpos[ids.cube_qpos:ids.cube_qpos + 3].copy(),
            "cube_quat": d.qpos[ids.cube_qpos + 3:ids.cube_qpos + 7].copy(),
            "target_pos": d.mocap_pos[ids.target_mocap].copy(),
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
                    self.model, CAMERAS, h, w, show_collision=self.visuals == "primitive",
                    shadows=self.task.shadows)
            t0 = time.perf_counter()
            self._frame = self._renderer.render(self.data)
            self.time_render += time.perf_counter() - t0
        return self._frame

    def render(self) -> np.ndarray | None:
        """front|side side by side, (H, 2W, 3) uint8 (render_mode="rgb_array")."""
        if self.render_mode != "rgb_array":
            gym.logger.warn("render() needs render_mode='rgb_array'; got None")
            return None
        return self._render_frame().copy()

    # ------------------------------------------------------------------------- reset / step
    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        task, m, d, ids, rng = self.task, self.model, self.data, self._ids, self.np_random
        # Draw every random number in a fixed order, whatever the options, so episodes depend
        # only on the seed.
        noise = rng.uniform(-task.rest_noise, task.rest_noise, size=6)
        cube = np.array([rng.uniform(*task.cube_x), rng.uniform(*task.cube_y),
                         rng.uniform(*task.cube_yaw)])
        target = np.array([rng.uniform(*task.target_x), rng.uniform(*task.target_y)])
        if self._workspace is None:
            self._workspace = workspace(m)
        cube, target = apply_reset_options(options, self._workspace, task.cube_size, cube,
                                           target)

        mujoco.mj_resetData(m, d)
        rest = np.clip(np.asarray(task.rest_pose) + noise, self.action_low, self.action_high)
        q = lerobot_to_radians(rest)
        d.qpos[ids.arm_qpos] = q
        d.ctrl[:] = q
        half = task.cube_size / 2
        yaw = np.deg2rad(cube[2])
        d.qpos[ids.cube_qpos:ids.cube_qpos + 7] = [cube[0], cube[1], half,
                                                   np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        d.mocap_pos[ids.target_mocap] = [target[0], target[1], 0.0]
        mujoco.mj_forward(m, d)

        self._step_count = 0
        self._clipped_total = 0
        self._tracker = _OutcomeTracker()
        self._frame = None
        self.initial_cube_pose = cube.copy()
        self.initial_target_pos = target.copy()
        info = {"is_success": False, "cube_pose": cube.copy(), "target_pos": target.copy()}
        return self._get_obs(), info

    def validate_action(self, action: Any) -> np.ndarray:
        """Return `action` as float64[6] or raise ValueError saying what was expected."""
        try:
            a = np.asarray(action)
        except Exception as exc:  # ragged lists and the like
            raise ValueError(f"action {action!r} is not an array; expected float32[6] joint "
                             f"targets ({', '.join(MOTOR_NAMES)})") from exc
        if a.shape != (6,):
            raise ValueError(f"action has shape {a.shape}; expected (6,) joint targets in "
                             f"LeRobot units ({', '.join(MOTOR_NAMES)})")
        if a.dtype.kind != "f":
            raise ValueError(f"action has dtype {a.dtype}; expected a floating-point array "
                             "(float32), e.g. np.asarray(action, dtype=np.float32)")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action contains NaN or inf: {a.tolist()}; expected finite joint "
                             "targets (degrees, gripper 0..100)")
        return a.astype(np.float64)

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
            success = False
        else:
            success = self._tracker.update(self, clipped)
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
        return self._get_obs(), float(success), terminated, truncated, info

    def _state_is_sane(self) -> bool:
        d, ids = self.data, self._ids
        if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))):
            return False
        cube_speed = np.linalg.norm(d.qvel[ids.cube_qvel:ids.cube_qvel + 3])
        return (np.max(np.abs(d.qvel[ids.arm_qvel])) < _MAX_JOINT_SPEED
                and cube_speed < _MAX_CUBE_SPEED)

    # ---------------------------------------------------------------- contact helpers
    def cube_contacts(self) -> tuple[bool, bool, bool]:
        """(fixed pad touches cube, moving pad touches cube, any robot geom touches cube)."""
        d, ids = self.data, self._ids
        fixed = moving = robot = False
        for i in range(d.ncon):
            c = d.contact[i]
            g1, g2 = c.geom1, c.geom2
            if ids.cube_geom not in (g1, g2):
                continue
            other = g2 if g1 == ids.cube_geom else g1
            if other in ids.robot_geoms:
                robot = True
                fixed |= other == ids.fixed_pad
                moving |= other == ids.moving_pad
        return fixed, moving, robot

    def pad_clearance(self) -> float:
        """Smallest distance between the cube and either finger pad (m), capped at 5 cm."""
        m, d, ids = self.model, self.data, self._ids
        return min(mujoco.mj_geomDistance(m, d, ids.cube_geom, pad, 0.05, None)
                   for pad in (ids.fixed_pad, ids.moving_pad))

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class _SceneIds:
    """Indices into the model that the env uses every step."""

    def __init__(self, m: mujoco.MjModel) -> None:
        self.arm_qpos_joints = np.array([m.joint(n).id for n in MOTOR_NAMES])
        self.arm_qpos = np.array([m.jnt_qposadr[j] for j in self.arm_qpos_joints])
        self.arm_qvel = np.array([m.jnt_dofadr[j] for j in self.arm_qpos_joints])
        cube_joint = m.joint("cube").id
        self.cube_qpos = int(m.jnt_qposadr[cube_joint])
        self.cube_qvel = int(m.jnt_dofadr[cube_joint])
        self.cube_geom = m.geom("cube").id
        self.fixed_pad = m.geom("fixed_pad").id
        self.moving_pad = m.geom("moving_pad").id
        self.target_mocap = int(m.body_mocapid[m.body("target").id])
        self.tcp_site = m.site("tcp").id
        base = m.body("base").id
        self.robot_geoms = frozenset(
            g for g in range(m.ngeom) if _is_descendant(m, m.geom_bodyid[g], base))


def _is_descendant(m: mujoco.MjModel, body: int, ancestor: int) -> bool:
    while body != 0:
        if body == ancestor:
            return True
        body = m.body_parentid[body]
    return False


class _OutcomeTracker:
    """Follows one episode to decide success and, at the end, why it failed."""

    def __init__(self) -> None:
        self.settled_steps = 0
        self.ever_lifted = False
        self.held = False
        self.dropped = False

    def update(self, env: PickPlaceEnv, action: np.ndarray) -> bool:
        task, state = env.task, env.task_state()
        cube, target = state["cube_pos"], state["target_pos"]
        half = task.cube_size / 2
        fixed, moving, robot = env.cube_contacts()
        lifted = cube[2] > half + 0.01
        held = fixed and moving
        if held and lifted:
            self.ever_lifted = True
        gripper_opening = action[5] > env.agent_pos()[5] + 2.0
        if self.held and not held and lifted and not gripper_opening:
            self.dropped = True  # the grasp slipped in the air while the gripper held on
        self.held = held
        speed = np.linalg.norm(env.data.qvel[env._ids.cube_qvel:env._ids.cube_qvel + 3])
        in_target = np.linalg.norm(cube[:2] - target[:2]) <= task.target_radius
        resting = cube[2] < half + 0.004 and speed < task.max_speed
        released = not robot and env.pad_clearance() >= task.release_clearance
        self.settled_steps = self.settled_steps + 1 if (in_target and resting and released) else 0
        return self.settled_steps >= task.settle_steps

    def failure_mode(self, env: PickPlaceEnv) -> str:
        state = env.task_state()
        in_target = (np.linalg.norm(state["cube_pos"][:2] - state["target_pos"][:2])
                     <= env.task.target_radius)
        if not self.ever_lifted:
            return "never_grasped"
        if self.held or in_target:
            return "timeout"  # still carrying, or on the target but not released/settled
        if self.dropped:
            return "dropped"
        return "misplaced"


def _check_image_size(image_size: Any) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in image_size)
        ok = all(int(v) == v for v in image_size)
    except (TypeError, ValueError):
        ok = False
    if not ok or not (16 <= h <= 2048 and 16 <= w <= 2048):
        raise ValueError(f"image_size={image_size!r} is invalid; expected (height, width) "
                         "integers in 16..2048, e.g. (480, 640) or (96, 128)")
    return h, w
