"""Success rules and failure modes, one tracker per task kind.

A tracker follows one episode: ``update(env, action)`` after every step returns
``(success, reward)``; ``failure_mode(env)`` names, at the end of a failed episode, why it
failed. Trackers read the env through its public helpers (``cube_pos``, ``cube_speed``,
``cube_contacts``, ``pad_clearance``, ``goal_pos``, ``cube_half``).

Success rules (all need the cubes released: no robot contact and both finger pads at least
``success.release_clearance`` away, and resting: speed below ``success.max_speed``, for
``success.settle_steps`` steps), except ``lift``:

- ``pick_place``: the cube's centre within ``target.radius`` of the pad's centre, on the table.
- ``lift``: the cube held between both pads at least ``success.lift_height`` above its resting
  height for ``success.hold_steps`` consecutive steps.
- ``stack``: the red cube resting on the blue one: centres within ``target.radius`` in x/y and
  the red cube's bottom on the blue cube's top.
- ``tidy``: every cube inside the box (centre within the inner walls, below their top).
  The reward is the fraction of cubes inside; the other tasks' reward is 1 on success, else 0.
"""

from __future__ import annotations

from typing import Any

import numpy as np

LIFTED = 0.01  # m above resting height that counts as lifted
ON_TABLE = 0.004  # m: a cube this close to its resting height is down

FAILURE_MODES: dict[str, tuple[str, ...]] = {
    "pick_place": ("never_grasped", "dropped", "misplaced", "timeout", "sim_unstable"),
    "lift": ("never_grasped", "dropped", "too_low", "timeout", "sim_unstable"),
    "stack": ("never_grasped", "dropped", "misplaced", "base_moved", "timeout",
              "sim_unstable"),
    "tidy": ("never_grasped", "dropped", "misplaced", "incomplete", "timeout", "sim_unstable"),
}


class _Grasp:
    """Grasp bookkeeping of one cube: ever lifted in the hand, dropped in the air."""

    def __init__(self) -> None:
        self.ever_lifted = False
        self.held = False
        self.dropped = False

    def update(self, env: Any, k: int, action: np.ndarray) -> tuple[bool, bool]:
        fixed, moving, robot = env.cube_contacts(k)
        lifted = env.cube_pos(k)[2] > env.cube_half(k) + LIFTED
        held = fixed and moving
        if held and lifted:
            self.ever_lifted = True
        gripper_opening = action[5] > env.agent_pos()[5] + 2.0
        if self.held and not held and lifted and not gripper_opening:
            self.dropped = True  # the grasp slipped in the air while the gripper held on
        self.held = held
        return held, robot


class PickPlaceOutcome:
    """pick_place: see the module docstring."""

    def __init__(self) -> None:
        self.settled_steps = 0
        self.grasp = _Grasp()

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]:
        task = env.task
        cube, target = env.cube_pos(0), env.goal_pos()
        half = env.cube_half(0)
        _, robot = self.grasp.update(env, 0, action)
        in_target = np.linalg.norm(cube[:2] - target[:2]) <= task.target_radius
        resting = cube[2] < half + ON_TABLE and env.cube_speed(0) < task.max_speed
        released = not robot and env.pad_clearance(0) >= task.release_clearance
        self.settled_steps = self.settled_steps + 1 if (in_target and resting and released) else 0
        success = self.settled_steps >= task.settle_steps
        return success, float(success)

    def failure_mode(self, env: Any) -> str:
        in_target = (np.linalg.norm(env.cube_pos(0)[:2] - env.goal_pos()[:2])
                     <= env.task.target_radius)
        g = self.grasp
        if not g.ever_lifted:
            return "never_grasped"
        if g.held or in_target:
            return "timeout"  # still carrying, or on the target but not released/settled
        if g.dropped:
            return "dropped"
        return "misplaced"


class LiftOutcome:
    """lift: see the module docstring."""

    def __init__(self) -> None:
        self.high_steps = 0
        self.ever_high = False
        self.grasp = _Grasp()

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]:
        held, _ = self.grasp.update(env, 0, action)
        high = held and env.cube_pos(0)[2] >= env.cube_half(0) + env.task.lift_height
        self.ever_high |= high
        self.high_steps = self.high_steps + 1 if high else 0
        success = self.high_steps >= env.task.hold_steps
        return success, float(success)

    def failure_mode(self, env: Any) -> str:
        g = self.grasp
        if not g.ever_lifted:
            return "never_grasped"
        if g.dropped:
            return "dropped"
        if not self.ever_high:
            return "too_low"
        return "timeout"  # was high, but not held there long enough


class StackOutcome:
    """stack: see the module docstring. Cube 0 is the red cube, cube 1 the blue base."""

    BASE_MOVED = 0.01  # m: the base cube pushed this far off its start counts as moved

    def __init__(self) -> None:
        self.settled_steps = 0
        self.grasp = _Grasp()
        self.base_start: np.ndarray | None = None

    def _on_base(self, env: Any) -> bool:
        red, blue = env.cube_pos(0), env.cube_pos(1)
        top = blue[2] + env.cube_half(1) + env.cube_half(0)
        return (np.linalg.norm(red[:2] - blue[:2]) <= env.task.target_radius
                and abs(red[2] - top) < ON_TABLE)

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]:
        task = env.task
        if self.base_start is None:
            self.base_start = env.cube_pos(1).copy()
        _, robot = self.grasp.update(env, 0, action)
        resting = max(env.cube_speed(0), env.cube_speed(1)) < task.max_speed
        released = not robot and env.pad_clearance(0) >= task.release_clearance
        ok = self._on_base(env) and resting and released
        self.settled_steps = self.settled_steps + 1 if ok else 0
        success = self.settled_steps >= task.settle_steps
        return success, float(success)

    def failure_mode(self, env: Any) -> str:
        g = self.grasp
        if not g.ever_lifted:
            return "never_grasped"
        if g.held or self._on_base(env):
            return "timeout"
        if g.dropped:
            return "dropped"
        start = self.base_start if self.base_start is not None else env.cube_pos(1)
        if np.linalg.norm(env.cube_pos(1)[:2] - start[:2]) > self.BASE_MOVED:
            return "base_moved"
        return "misplaced"


class TidyOutcome:
    """tidy: see the module docstring."""

    def __init__(self) -> None:
        self.settled_steps = 0
        self.grasps: list[_Grasp] = []

    def inside(self, env: Any, k: int) -> bool:
        """Cube `k`'s centre is within the box's inner walls and below their top."""
        cube, box = env.cube_pos(k), env.goal_pos()
        return bool(np.all(np.abs(cube[:2] - box[:2]) <= env.task.target_radius)
                    and cube[2] < env.task.wall_height)

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]:
        task = env.task
        n = task.n_cubes
        if not self.grasps:
            self.grasps = [_Grasp() for _ in range(n)]
        all_ok, n_inside = True, 0
        for k, g in enumerate(self.grasps):
            _, robot = g.update(env, k, action)
            inside = self.inside(env, k)
            n_inside += inside
            released = not robot and env.pad_clearance(k) >= task.release_clearance
            all_ok &= inside and released and env.cube_speed(k) < task.max_speed
        self.settled_steps = self.settled_steps + 1 if all_ok else 0
        success = self.settled_steps >= task.settle_steps
        return success, 1.0 if success else n_inside / n

    def failure_mode(self, env: Any) -> str:
        n = env.task.n_cubes
        inside = [self.inside(env, k) for k in range(n)]
        if all(inside) or any(g.held for g in self.grasps):
            return "timeout"
        if not any(g.ever_lifted for g in self.grasps):
            return "never_grasped"
        if any(g.dropped for g in self.grasps):
            return "dropped"
        if any(g.ever_lifted and not inside[k] for k, g in enumerate(self.grasps)):
            return "misplaced"  # carried, then left outside the box
        return "incomplete"  # the cubes that were moved are in; others were never picked


_TRACKERS = {"pick_place": PickPlaceOutcome, "lift": LiftOutcome, "stack": StackOutcome,
             "tidy": TidyOutcome}


def make_tracker(kind: str) -> Any:
    """A fresh outcome tracker for a task of `kind`."""
    return _TRACKERS[kind]()
