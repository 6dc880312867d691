"""Scripted pick-and-place expert for `so101_sim/PickPlace-v0`.

It reads the true cube and target poses from the observation's ``environment_state`` (use
``obs_type="pixels_agent_pos_env_state"`` or ``"state"``) and the arm's ``agent_pos``, plans
top-down grasp and place poses with MuJoCo-Jacobian IK, and follows smooth joint-space
segments at the env's control rate: approach above the cube, descend, close, lift, carry,
lower onto the target, release, retreat. Outputs are the env's actions (LeRobot units).

With ``recover=True`` it also watches the cube (it knows its pose) and tries again when
something went wrong: a grasp that did not lift the cube, a cube dropped on the way, or a cube
left off the target once the plan has run out. It backs off (gripper open, tool raised),
waits for the cube to settle, and plans pick-and-place anew from where things are. Recorded
with DART noise, so that some first attempts fail, this puts recoveries into the demos.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from so101_sim.kinematics import TopDownIK
from so101_sim.scene import build_model
from so101_sim.task import TaskSpec, load_task
from so101_sim.units import lerobot_to_radians, radians_to_lerobot

FIXED_PAD_FACE_X = -0.0095  # gripper-frame x of the fixed pad's inner face (assets/so101.xml)
TCP_X = 0.002  # gripper-frame x of the `tcp` site
OPEN = 45.0  # gripper opening for approach/release (LeRobot units): ~5 cm between pads
CLOSED = 0.0
LIFTED = 0.01  # m above resting height: the cube counts as lifted (the env's own rule)
BACKOFF_RISE = 0.05  # m the tool rises, gripper opening, before a retry
SETTLE_STEPS = 8  # control steps after the plan ends before a cube off the target counts
RETRY_SPEED = np.array([0.6, 0.7, 0.7, 1.0, 1.0, 1.0, 0.7, 0.6])  # segment duration factors


@dataclass
class _Segment:
    name: str
    steps: int
    target: np.ndarray  # (6,) LeRobot units at the end of the segment


class ScriptedExpert:
    """Policy-like object: ``reset(seed)`` then ``select_action(obs)`` every step."""

    def __init__(self, task: str | TaskSpec = "pick_place", clearance: float = 0.004,
                 hover: float = 0.06, carry_height: float = 0.08, jitter: bool = True,
                 recover: bool = False, max_retries: int = 2) -> None:
        self.task = load_task(task)
        model, _ = build_model(self.task)
        self.ik = TopDownIK(model)
        self.clearance, self.base_hover, self.base_carry = clearance, hover, carry_height
        self.jitter = jitter
        self.recover, self.max_retries = recover, max_retries
        self.retries = 0  # retries started in this episode
        self.retry_log: list[str] = []  # why each retry started ("missed", "dropped", ...)
        self._replan = False  # plan anew (from the current state) when the segments run out
        self._prev_cube: np.ndarray | None = None
        self.hover, self.carry_height = hover, carry_height
        self._speed = np.ones(8)
        self._segments: list[_Segment] = []
        self._t = 0
        self._start = np.zeros(6)

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode; with `jitter`, speed and waypoints vary per seed so the demos
        are not one trajectory (same seed, same jitter)."""
        self._segments = []
        self._t = 0
        self.retries, self.retry_log, self._replan, self._prev_cube = 0, [], False, None
        self.hover, self.carry_height, self._speed = self.base_hover, self.base_carry, np.ones(8)
        if self.jitter:
            rng = np.random.default_rng(seed)
            self.hover = self.base_hover + rng.uniform(-0.015, 0.015)
            self.carry_height = self.base_carry + rng.uniform(-0.02, 0.02)
            # Duration factors per segment; moves with the cube in hand are only slowed down
            # (faster carries throw the cube).
            lo = np.array([0.8, 0.85, 1.0, 1.0, 1.0, 1.0, 0.9, 0.8])
            self._speed = rng.uniform(lo, lo + 0.35)

    def _plan(self, agent_pos: np.ndarray, env_state: np.ndarray) -> None:
        half = self.task.cube_size / 2
        cube, quat, target = env_state[:3].astype(float), env_state[3:7], env_state[7:10]
        w, x, y, z = quat
        cube_yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        q_now = lerobot_to_radians(agent_pos)[:5]
        seed_q = np.deg2rad([0.0, 0.0, 0.0, 90.0, q_now[4] * 180 / np.pi])

        # Of the cube's four face-aligned yaws, take the one needing the least wrist roll.
        sols = []
        for k in range(4):
            yaw = cube_yaw + k * np.pi / 2
            grasp_offset = (FIXED_PAD_FACE_X + half + self.clearance) - TCP_X
            axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            above = cube + np.array([0, 0, self.hover]) - grasp_offset * axis
            q, err = self.ik.solve(above, yaw, seed_q)
            sols.append((err > 2e-3, abs(q[4] - q_now[4]), yaw, axis, grasp_offset, q))
        _, _, yaw, axis, grasp_offset, q_above = min(sols, key=lambda s: (s[0], s[1]))

        grasp = cube + np.array([0, 0, 0.002]) - grasp_offset * axis
        q_grasp, _ = self.ik.solve(grasp, yaw, q_above)
        # Place: the cube (not the tool) goes onto the target centre.
        place_xy = np.asarray(target[:2]) - grasp_offset * axis[:2]
        # Carry as high as asked where the arm reaches straight up over both ends; far
        # corners of the workspace are lower (an unreachable waypoint would swing the cube).
        height = self.carry_height
        while True:
            q_lift, err_lift = self.ik.solve(grasp + np.array([0, 0, height]), yaw, q_grasp)
            q_carry, err_carry = self.ik.solve(np.r_[place_xy, grasp[2] + height], yaw, q_lift)
            if max(err_lift, err_carry) < 2e-3 or height <= 0.04:
                break
            height -= 0.01
        q_place, _ = self.ik.solve(np.r_[place_xy, grasp[2] + 0.004], yaw, q_carry)

        def act(q5: np.ndarray, grip: float) -> np.ndarray:
            return np.r_[radians_to_lerobot(np.r_[q5, 0.0])[:5], grip]

        plan = [
            ("approach", 35, act(q_above, OPEN)),
            ("descend", 20, act(q_grasp, OPEN)),
            ("close", 12, act(q_grasp, CLOSED)),
            ("lift", 20, act(q_lift, CLOSED)),
            ("carry", 35, act(q_carry, CLOSED)),
            ("lower", 20, act(q_place, CLOSED)),
            ("release", 10, act(q_place, OPEN)),
            ("retreat", 15, act(q_carry, OPEN)),
        ]
        # A retry moves faster (episodes are capped at the task's max_steps) but carries no
        # faster than the first attempt's slowest jitter allows.
        speed = np.minimum(self._speed, RETRY_SPEED) if self.retries else self._speed
        self._segments = [_Segment(name, max(4, round(steps * k)), target)
                          for (name, steps, target), k in zip(plan, speed, strict=True)]
        self._start = np.asarray(agent_pos, dtype=np.float64).copy()
        self._t = 0

    @property
    def phase(self) -> str:
        t = self._t
        for seg in self._segments:
            if t < seg.steps:
                return seg.name
            t -= seg.steps
        return "done"

    def select_action(self, obs: dict) -> np.ndarray:
        """Next action (float32[6], LeRobot units) from the observation dict."""
        if "environment_state" not in obs:
            raise ValueError("ScriptedExpert needs obs['environment_state']: create the env with "
                             "obs_type='pixels_agent_pos_env_state' or 'state'")
        agent_pos = np.asarray(obs["agent_pos"])
        env_state = np.asarray(obs["environment_state"])
        if not self._segments or (self._replan and self.phase == "done"):
            self._replan = False
            self._plan(agent_pos, env_state)
        elif self.recover:
            self._watch(agent_pos, env_state)
        t, start = self._t, self._start
        self._t += 1
        for seg in self._segments:
            if t < seg.steps:
                s = (t + 1) / seg.steps
                s = s * s * (3 - 2 * s)  # smoothstep: zero velocity at both ends
                return (start + s * (seg.target - start)).astype(np.float32)
            t -= seg.steps
            start = seg.target
        return start.astype(np.float32)

    # ------------------------------------------------------------------------- recoveries
    def _watch(self, agent_pos: np.ndarray, env_state: np.ndarray) -> None:
        """Start a retry when the cube shows the plan has failed (see the module docstring)."""
        cube = env_state[:3]
        moving = (self._prev_cube is not None
                  and np.linalg.norm(cube - self._prev_cube) > 1e-3)  # > 3 cm/s
        self._prev_cube = cube.copy()
        if self._replan or self.retries >= self.max_retries:
            return
        rest_z = self.task.cube_size / 2
        phase, lifted = self.phase, cube[2] > rest_z + LIFTED
        if phase == "carry" and not lifted and not moving:
            self._retry(agent_pos, "missed" if self._phase_time() <= 1 else "dropped")
        elif phase == "done" and self._t - self._plan_steps() >= SETTLE_STEPS and not moving:
            self._retry(agent_pos, "misplaced")

    def _plan_steps(self) -> int:
        return sum(seg.steps for seg in self._segments)

    def _phase_time(self) -> int:
        t = self._t
        for seg in self._segments:
            if t < seg.steps:
                return t
            t -= seg.steps
        return t

    def _retry(self, agent_pos: np.ndarray, why: str) -> None:
        """Open the gripper and raise the tool straight up, then plan anew from there."""
        q_now = lerobot_to_radians(agent_pos)[:5]
        pos, rot = self.ik.tcp_pose(q_now)
        yaw = float(np.arctan2(rot[1, 0], rot[0, 0]))
        q_up, _ = self.ik.solve(pos + np.array([0.0, 0.0, BACKOFF_RISE]), yaw, q_now)
        target = np.r_[radians_to_lerobot(np.r_[q_up, 0.0])[:5], OPEN]
        self._segments = [_Segment("backoff", 12, target)]
        self._start = np.asarray(agent_pos, dtype=np.float64).copy()
        self._t = 0
        self._replan = True
        self.retries += 1
        self.retry_log.append(why)
