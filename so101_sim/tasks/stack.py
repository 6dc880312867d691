"""stack: put the red cube on top of the blue cube.

**Description.** A red cube and a larger blue base cube on the table, no pad; the arm lifts
the red cube over the blue one and lowers it onto its top face.

**Randomizations.** The red cube's x, y and yaw from ``[cube]``; the blue cube's x, y from
``[target]`` and its yaw from ``[cube] yaw``; both within ``[layout] reach`` and at least
``min_separation`` apart. The goal (``goal_pos``) is where the red cube's centre belongs: on
top of the blue cube, wherever it has been pushed.

**Success.** The red cube's centre within ``target.radius`` of the blue cube's in x/y, its
bottom on the blue cube's top, both resting, released, for ``success.settle_steps`` steps.
Failure modes: ``never_grasped``, ``dropped``, ``misplaced``, ``base_moved`` (the blue cube
pushed more than 1 cm), ``timeout``, ``sim_unstable``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from so101_sim.tasks.kind import TaskKind, register_kind
from so101_sim.tasks.layouts import Layout
from so101_sim.tasks.outcomes import ON_TABLE, Grasp, Settle, released
from so101_sim.tasks.props import add_cube, remove_target_pad

BASE_CUBE_RGBA = (0.1, 0.25, 0.85, 1)
BASE_MOVED = 0.01  # m: the base cube pushed this far off its start counts as moved


class StackOutcome:
    """Cube 0 is the red cube, cube 1 the blue base."""

    def __init__(self) -> None:
        self.settle = Settle()
        self.grasp = Grasp()
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
        ok = self._on_base(env) and resting and released(env, 0, robot)
        success = self.settle.update(ok, task.settle_steps)
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
        if np.linalg.norm(env.cube_pos(1)[:2] - start[:2]) > BASE_MOVED:
            return "base_moved"
        return "misplaced"


@register_kind
class Stack(TaskKind):
    name = "stack"
    failure_modes: ClassVar[tuple[str, ...]] = ("never_grasped", "dropped", "misplaced",
                                                "base_moved", "timeout", "sim_unstable")
    place_among_objects: ClassVar[bool] = True

    def draw(self, spec: Any, rng: np.random.Generator) -> Layout:
        layout = super().draw(spec, rng)
        base = [layout.target[0], layout.target[1], rng.uniform(*spec.cube_yaw)]
        layout.cubes = np.vstack([layout.cubes, base])  # the base stands on the target spot
        return layout

    def layout_points(self, spec: Any, layout: Layout) -> list[np.ndarray]:
        return [c[:2] for c in layout.cubes]

    def cube_names(self, spec: Any) -> list[str]:
        return [*super().cube_names(spec), "base_cube"]

    def cube_sizes(self, spec: Any, cube_size: float | None = None) -> list[float]:
        return [*super().cube_sizes(spec, cube_size), spec.base_size]

    def furnish(self, mjspec: Any, spec: Any) -> None:
        remove_target_pad(mjspec)
        mass = spec.cube_mass * (spec.base_size / spec.cube_size) ** 3  # same density
        add_cube(mjspec, "base_cube", spec.base_size, mass, BASE_CUBE_RGBA,
                 [0.2, -0.1, spec.base_size / 2])

    def goal_pos(self, env: Any) -> np.ndarray:
        return env.cube_pos(1) + np.array([0, 0, env.cube_half(1) + env.cube_half(0)])

    def tracker(self) -> StackOutcome:
        return StackOutcome()

    def place(self, spec: Any, env_state: np.ndarray, cube: np.ndarray,
              stage: int) -> tuple[np.ndarray, float]:
        target = env_state[7:10]
        return target[:2], float(target[2] - cube[2])
