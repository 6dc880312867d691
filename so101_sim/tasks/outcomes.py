"""What every success tracker shares: grasp bookkeeping and the resting/lifted thresholds.

Each kind's tracker (in its own file) follows one episode: ``update(env, action)`` after every
step returns ``(success, reward)``; ``failure_mode(env)`` names, at the end of a failed
episode, why it failed. Trackers read the env through its public helpers (``cube_pos``,
``cube_speed``, ``cube_contacts``, ``pad_clearance``, ``goal_pos``, ``cube_half``).

Success needs the cubes released (no robot contact and both finger pads at least
``success.release_clearance`` away) and resting (speed below ``success.max_speed``) for
``success.settle_steps`` steps, except where a kind says otherwise (``lift``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

LIFTED = 0.01  # m above resting height that counts as lifted
ON_TABLE = 0.004  # m: a cube this close to its resting height is down


class Grasp:
    """Grasp bookkeeping of one cube: ever lifted in the hand, dropped in the air."""

    def __init__(self) -> None:
        self.ever_lifted = False
        self.held = False
        self.dropped = False

    def update(self, env: Any, k: int, action: np.ndarray) -> tuple[bool, bool]:
        """Follow cube `k` one step; returns (held between both pads, touched by the robot)."""
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


def released(env: Any, k: int, touched: bool) -> bool:
    """Cube `k` is free of the robot and both pads are at least release_clearance away."""
    return not touched and env.pad_clearance(k) >= env.task.release_clearance


class Settle:
    """Counts consecutive steps a condition held; success once it held settle_steps."""

    def __init__(self) -> None:
        self.steps = 0

    def update(self, ok: bool, needed: int) -> bool:
        self.steps = self.steps + 1 if ok else 0
        return self.steps >= needed
