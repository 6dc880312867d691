"""Scripted expert for every task of `so101_sim/PickPlace-v0` (``envs/*.toml``).

It reads the true cube and goal poses from the observation's ``environment_state`` (use
``obs_type="pixels_agent_pos_env_state"`` or ``"state"``) and the arm's ``agent_pos``, plans
top-down grasp and place poses with MuJoCo-Jacobian IK, and follows smooth joint-space
segments at the env's control rate: approach above the cube, descend, close, lift, carry,
lower onto the target, release, retreat. Outputs are the env's actions (LeRobot units).
The task's kind (``so101_sim.tasks.TaskKind``) says where each cube goes (``place``), how
many cubes it moves in turn (``stages``), whether the place is among other objects (carry
clear, re-aim as the lowering starts, retreat straight up) and may replace the plan's
segments (``expert_plan``: ``lift`` grasps, lifts and holds).

With ``recover=True`` it also watches the cube (it knows its pose) and tries again when
something went wrong: a grasp that did not lift the cube, a cube dropped on the way, or a cube
left off the target once the plan has run out. It backs off (gripper open, tool raised),
waits for the cube to settle, and plans pick-and-place anew from where things are. Recorded
with DART noise, so that some first attempts fail, this puts recoveries into the demos.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from so101_sim.expert.kinematics import TopDownIK
from so101_sim.tasks import DEFAULT_TASK, PlanContext, TaskSpec, get_kind, load_task

if TYPE_CHECKING:
    import mujoco
from so101_sim.utils.units import lerobot_to_radians, radians_to_lerobot

FIXED_PAD_FACE_X = -0.0095  # gripper-frame x of the fixed pad's inner face (assets/so101.xml)
TCP_X = 0.002  # gripper-frame x of the `tcp` site
OPEN = 45.0  # gripper opening for approach/release (LeRobot units): ~5 cm between pads
CLOSED = 0.0
LIFTED = 0.01  # m above resting height: the cube counts as lifted (the env's own rule)
BACKOFF_RISE = 0.05  # m the tool rises, gripper opening, before a retry
SETTLE_STEPS = 8  # control steps after the plan ends before a cube off the target counts
RETRY_SPEED = np.array([0.6, 0.7, 0.7, 1.0, 1.0, 1.0, 0.7, 0.6])  # segment duration factors
CARRY_CLEARANCE = 0.04  # m the carried cube's bottom stays above the place (stack, tidy)
MIN_HOVER = 0.03  # m: the lowest approach height above the cube, where higher is out of reach
RETREAT_RISE = 0.05  # m above the place the open gripper retreats to (stack, tidy)


@dataclass
class _Segment:
    name: str
    steps: int
    target: np.ndarray  # (6,) LeRobot units at the end of the segment


class ScriptedExpert:
    """Policy-like object: ``reset(seed)`` then ``select_action(obs)`` every step."""

    def __init__(self, task: str | TaskSpec = DEFAULT_TASK, clearance: float = 0.004,
                 hover: float = 0.06, carry_height: float = 0.08, jitter: bool = True,
                 recover: bool = False, max_retries: int = 2,
                 model: mujoco.MjModel | None = None) -> None:
        self.task = load_task(task)
        self.kind = get_kind(self.task.kind)
        if model is None:  # no env at hand: compile the scene once for its kinematics
            from so101_sim.sim.scene import build_model

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
        self._stage = 0  # index of the cube being moved (tidy moves several in turn)
        self._place_goal = (0.0, 0.0)  # (resting height of the cube, grasp yaw) of the plan
        # A randomized cube size is read off the resting cube's height (see _cube_half).
        rnd = self.task.randomize
        self._size_from_state = rnd is not None and rnd.cube_size is not None

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode; with `jitter`, speed and waypoints vary per seed so the demos
        are not one trajectory (same seed, same jitter)."""
        self._segments = []
        self._t = 0
        self._stage = 0
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

    def _cube_slice(self, k: int) -> slice:
        """Cube `k`'s position+quaternion in environment_state (the goal sits after cube 0)."""
        start = 0 if k == 0 else 10 + 7 * (k - 1)
        return slice(start, start + 7)

    def _cube_half(self, cube: np.ndarray) -> float:
        if self._size_from_state:
            return float(cube[2])  # planned while the cube rests: its height is half its size
        return self.task.cube_size / 2

    def _place(self, env_state: np.ndarray, cube: np.ndarray) -> tuple[np.ndarray, float]:
        """Where the cube goes: (x, y of its centre, height above its start)."""
        return self.kind.place(self.task, env_state, cube, self._stage)

    def _plan(self, agent_pos: np.ndarray, env_state: np.ndarray) -> None:
        part = env_state[self._cube_slice(self._stage)]
        cube, quat = part[:3].astype(float), part[3:7]
        half = self._cube_half(cube)
        place_target, place_rise = self._place(env_state, cube)
        w, x, y, z = quat
        cube_yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        q_now = lerobot_to_radians(agent_pos)[:5]
        seed_q = np.deg2rad([0.0, 0.0, 0.0, 90.0, q_now[4] * 180 / np.pi])

        grasp_offset = (FIXED_PAD_FACE_X + half + self.clearance) - TCP_X
        if self.task.reach is not None:
            yaw, axis, q_above = self._edge_aware_grasp(cube, cube_yaw, grasp_offset,
                                                        place_target, place_rise, q_now, seed_q)
        else:
            # Of the cube's four face-aligned yaws, take the one needing the least wrist roll.
            sols = []
            for k in range(4):
                yaw = cube_yaw + k * np.pi / 2
                axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
                above = cube + np.array([0, 0, self.hover]) - grasp_offset * axis
                q, err = self.ik.solve(above, yaw, seed_q)
                sols.append((err > 2e-3, abs(q[4] - q_now[4]), yaw, axis, q))
            _, _, yaw, axis, q_above = min(sols, key=lambda s: (s[0], s[1]))

        grasp = cube + np.array([0, 0, 0.002]) - grasp_offset * axis
        q_grasp, _ = self.ik.solve(grasp, yaw, q_above)
        # Place: the cube (not the tool) goes onto the target centre.
        place_xy = np.asarray(place_target) - grasp_offset * axis[:2]
        # Carry as high as asked where the arm reaches straight up over both ends; far
        # corners of the workspace are lower (an unreachable waypoint would swing the cube).
        if not self.kind.place_among_objects:
            height = self.carry_height
            while True:
                q_lift, err_lift = self.ik.solve(grasp + np.array([0, 0, height]), yaw, q_grasp)
                q_carry, err_carry = self.ik.solve(np.r_[place_xy, grasp[2] + height], yaw,
                                                   q_lift)
                if max(err_lift, err_carry) < 2e-3 or height <= 0.04:
                    break
                height -= 0.01
        else:
            q_lift, q_carry = self._lift_and_carry(grasp, place_xy, place_rise, yaw, q_grasp)
        q_place, _ = self.ik.solve(np.r_[place_xy, grasp[2] + 0.004 + place_rise], yaw, q_carry)
        self._place_goal = (float(cube[2]), yaw)  # for _correct_place
        q_retreat = q_carry
        if self.kind.place_among_objects:  # rise clear of a cube placed high or in a box
            q_retreat = self._retreat_pose(np.r_[place_xy, grasp[2] + place_rise], yaw, q_place)

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
            ("retreat", 15, act(q_retreat, OPEN)),
        ]
        plan = self.kind.expert_plan(self.task, plan, PlanContext(
            self.ik, grasp, yaw, q_grasp, self.carry_height, act, CLOSED, OPEN))
        # A retry moves faster (episodes are capped at the task's max_steps) but carries no
        # faster than the first attempt's slowest jitter allows.
        speed = np.minimum(self._speed, RETRY_SPEED) if self.retries else self._speed
        self._segments = [_Segment(name, max(4, round(steps * k)), target)
                          for (name, steps, target), k in zip(plan, speed, strict=False)]
        self._start = np.asarray(agent_pos, dtype=np.float64).copy()
        self._t = 0

    def _edge_aware_grasp(self, cube: np.ndarray, cube_yaw: float, grasp_offset: float,
                          place_target: np.ndarray, place_rise: float, q_now: np.ndarray,
                          seed_q: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """(yaw, jaw axis, approach pose) for tasks with a [layout] reach rule: objects out to
        the edge of the reach, and places far from the grasp. Of the four face-aligned yaws,
        one the arm reaches top-down at the grasp *and* at the place (the wrist roll has to
        turn with the pan on the way: one yaw may run into its limit), the least wrist roll
        first; the approach as high as ``hover`` where the arm reaches that high. pick_place
        (no reach rule) keeps the plain choice its recorded demos used."""
        sols = []
        for k in range(4):
            yaw = cube_yaw + k * np.pi / 2
            axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            grasp = cube + np.array([0, 0, 0.002]) - grasp_offset * axis
            q_grasp, err_grasp = self.ik.solve(grasp, yaw, seed_q)
            place = np.r_[np.asarray(place_target) - grasp_offset * axis[:2],
                          grasp[2] + place_rise + CARRY_CLEARANCE]
            _, err_place = self.ik.solve(place, yaw, q_grasp)
            err = max(err_grasp, err_place)
            sols.append((err > 2e-3, err if err > 2e-3 else 0.0, abs(q_grasp[4] - q_now[4]),
                         yaw, axis, q_grasp))
        *_, yaw, axis, q_grasp = min(sols, key=lambda s: s[:3])
        hover = self.hover
        while True:
            above = cube + np.array([0, 0, hover]) - grasp_offset * axis
            q_above, err = self.ik.solve(above, yaw, q_grasp)
            if err < 2e-3 or hover <= MIN_HOVER:
                return yaw, axis, q_above
            hover -= 0.01

    def _lift_and_carry(self, grasp: np.ndarray, place_xy: np.ndarray, place_rise: float,
                        yaw: float, q_grasp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lift and carry-end poses chosen separately, each as high as the arm reaches there
        top-down, the carry end at least CARRY_CLEARANCE above the place (stack's base cube,
        tidy's walls): a low carry would sweep the cube through them."""
        lowest = place_rise + CARRY_CLEARANCE
        height, q_lift = self.carry_height, q_grasp
        while True:
            q_lift, err = self.ik.solve(grasp + np.array([0, 0, height]), yaw, q_grasp)
            if err < 2e-3 or height <= 0.04:
                break
            height -= 0.01
        height = max(self.carry_height, lowest)
        while True:
            q_carry, err = self.ik.solve(np.r_[place_xy, grasp[2] + height], yaw, q_lift)
            if err < 2e-3 or height <= lowest:
                return q_lift, q_carry
            height -= 0.01

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
        elif self.phase == "done" and self._stage + 1 < self.kind.stages(self.task):
            self._stage += 1  # tidy: the next cube, planned from where things are now
            self._plan(agent_pos, env_state)
        elif (self.kind.place_among_objects and self.phase == "lower"
              and self._phase_time() == 0):
            self._correct_place(agent_pos, env_state)
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

    def _retreat_pose(self, tool: np.ndarray, yaw: float, q_place: np.ndarray) -> np.ndarray:
        """Straight up from the place by RETREAT_RISE, or less where the arm reaches less high,
        or else up and back from the fixed jaw's side (the open moving jaw has room): an
        unreachable target would swing the open jaws sideways through the placed cube."""
        back = -np.array([np.cos(yaw), np.sin(yaw), 0.0])  # away from the fixed pad
        for shift in (0.0, 0.01, 0.02):
            for rise in (RETREAT_RISE, 0.04, 0.03, 0.02):
                q_up, err = self.ik.solve(tool + shift * back + np.array([0, 0, rise]), yaw,
                                          q_place)
                if err < 2e-3:
                    return q_up
        return q_place

    def _correct_place(self, agent_pos: np.ndarray, env_state: np.ndarray) -> None:
        """stack, tidy: as the lowering starts, aim it by where the cube actually sits in the
        hand (closing the jaws can shift it by a centimetre), not where the plan put it."""
        rest_z, yaw = self._place_goal
        # The goal as it is now (stack's base cube may have been nudged since the plan).
        xy_goal, rise = self._place(env_state, np.array([0.0, 0.0, rest_z]))
        z_goal = rest_z + 0.004 + rise
        q_now = lerobot_to_radians(agent_pos)[:5]
        tcp, _ = self.ik.tcp_pose(q_now)
        in_hand = env_state[self._cube_slice(self._stage)][:3] - tcp
        tool = np.r_[xy_goal - in_hand[:2], z_goal - in_hand[2]]
        q_place, err = self.ik.solve(tool, yaw, q_now)
        if err > 2e-3:
            return  # out of reach: keep the plan
        q_up = self._retreat_pose(tool, yaw, q_place)
        for seg in self._segments:
            if seg.name in ("lower", "release", "retreat"):
                q = q_up if seg.name == "retreat" else q_place
                seg.target = np.r_[radians_to_lerobot(np.r_[q, 0.0])[:5], seg.target[5]]

    # ------------------------------------------------------------------------- recoveries
    def _watch(self, agent_pos: np.ndarray, env_state: np.ndarray) -> None:
        """Start a retry when the cube shows the plan has failed (see the module docstring)."""
        cube = env_state[self._cube_slice(self._stage)][:3]
        moving = (self._prev_cube is not None
                  and np.linalg.norm(cube - self._prev_cube) > 1e-3)  # > 3 cm/s
        self._prev_cube = cube.copy()
        if self._replan or self.retries >= self.max_retries:
            return
        rest_z = self.task.cube_size / 2
        phase, lifted = self.phase, cube[2] > rest_z + LIFTED
        if phase == "carry" and not lifted and not moving:
            self._retry(agent_pos, "missed" if self._phase_time() <= 1 else "dropped")
        elif (phase == "done" and self.kind.retry_misplaced
              and self._t - self._plan_steps() >= SETTLE_STEPS and not moving):
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
