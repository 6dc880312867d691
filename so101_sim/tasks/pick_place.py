"""pick_place: pick the red cube up and put it on the green pad.

**Description.** One red cube and a green target pad on the table; the arm grasps the cube
top-down, carries it over the pad and releases it there.

**Randomizations.** The cube's x, y and yaw from ``[cube]``; the pad's x, y from ``[target]``
(fixed in ``pick_place.toml``, drawn over the workspace in ``pick_place_anywhere.toml``);
optionally the look and physics of the scene (``[randomize]``, ``pick_place_dr.toml``).

**Success.** The cube's centre within ``target.radius`` of the pad's centre, resting on the
table, released, for ``success.settle_steps`` steps. Failure modes: ``never_grasped``,
``dropped``, ``misplaced`` (carried, then left off the pad), ``timeout`` (still carrying, or on
the pad but not released and settled), ``sim_unstable``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from so101_sim.tasks.kind import TaskKind, register_kind
from so101_sim.tasks.outcomes import ON_TABLE, Grasp, Settle, released


class PickPlaceOutcome:
    def __init__(self) -> None:
        self.settle = Settle()
        self.grasp = Grasp()

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]:
        task = env.task
        cube, target = env.cube_pos(0), env.goal_pos()
        _, robot = self.grasp.update(env, 0, action)
        in_target = np.linalg.norm(cube[:2] - target[:2]) <= task.target_radius
        resting = cube[2] < env.cube_half(0) + ON_TABLE and env.cube_speed(0) < task.max_speed
        ok = in_target and resting and released(env, 0, robot)
        success = self.settle.update(ok, task.settle_steps)
        return success, float(success)

    def failure_mode(self, env: Any) -> str:
        in_target = (np.linalg.norm(env.cube_pos(0)[:2] - env.goal_pos()[:2])
                     <= env.task.target_radius)
        g = self.grasp
        if not g.ever_lifted:
            return "never_grasped"
        if g.held or in_target:
            return "timeout"
        if g.dropped:
            return "dropped"
        return "misplaced"


@register_kind
class PickPlace(TaskKind):
    """The default kind: the scene as ``assets/scene_pick_place.xml`` writes it."""

    name = "pick_place"
    retry_misplaced: ClassVar[bool] = True

    def tracker(self) -> PickPlaceOutcome:
        return PickPlaceOutcome()
