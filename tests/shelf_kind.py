"""A task kind defined outside the package, as a user would: put the cube on a shelf.

docs/architecture.md walks through this file ("Adding a task kind"); tests/test_task_kinds.py
loads it by name from a task TOML, steps it, scores it and solves it with the scripted expert.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from so101_sim.tasks import TaskKind, register_kind
from so101_sim.tasks.outcomes import ON_TABLE, Grasp, Settle, released
from so101_sim.tasks.props import remove_target_pad

SHELF_HALF = (0.03, 0.03, 0.01)  # m: a 6 x 6 cm board standing 2 cm high
SHELF_GAP = 0.001  # m above the table: the static board never touches it


def shelf_top() -> float:
    return SHELF_GAP + 2 * SHELF_HALF[2]


class ShelfOutcome:
    """Success: the cube resting on the shelf's top, within target.radius of its centre."""

    def __init__(self) -> None:
        self.settle = Settle()
        self.grasp = Grasp()

    def _on_shelf(self, env: Any) -> bool:
        cube, goal = env.cube_pos(0), env.goal_pos()
        return bool(np.linalg.norm(cube[:2] - goal[:2]) <= env.task.target_radius
                    and abs(cube[2] - goal[2]) < ON_TABLE)

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]:
        _, touched = self.grasp.update(env, 0, action)
        ok = (self._on_shelf(env) and env.cube_speed(0) < env.task.max_speed
              and released(env, 0, touched))
        success = self.settle.update(ok, env.task.settle_steps)
        return success, float(success)

    def failure_mode(self, env: Any) -> str:
        if not self.grasp.ever_lifted:
            return "never_grasped"
        if self.grasp.held or self._on_shelf(env):
            return "timeout"
        return "dropped" if self.grasp.dropped else "misplaced"


@register_kind
class Shelf(TaskKind):
    name = "shelf"
    place_among_objects: ClassVar[bool] = True  # carry clear of the board, retreat upwards

    def furnish(self, mjspec: Any, spec: Any) -> None:
        import mujoco

        remove_target_pad(mjspec)
        mjspec.body("target").add_geom(
            name="shelf", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(SHELF_HALF),
            pos=[0, 0, SHELF_GAP + SHELF_HALF[2]], rgba=[0.55, 0.35, 0.2, 1], condim=4)

    def goal_pos(self, env: Any) -> np.ndarray:
        """Where the cube's centre belongs: on the board's top."""
        target = env.data.mocap_pos[env.ids.target_mocap]
        return target + np.array([0.0, 0.0, shelf_top() + env.cube_half(0)])

    def tracker(self) -> ShelfOutcome:
        return ShelfOutcome()

    def place(self, spec: Any, env_state: np.ndarray, cube: np.ndarray,
              stage: int) -> tuple[np.ndarray, float]:
        goal = env_state[7:10]
        return goal[:2], float(goal[2] - cube[2])  # the cube's centre rises onto the board
