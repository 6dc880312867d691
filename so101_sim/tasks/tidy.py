"""tidy: put all the cubes into the box.

**Description.** Three cubes (red, orange, purple) and an open box with low walls; the arm
lifts each cube over the wall into its own slot of the box.

**Randomizations.** Each cube's x, y and yaw from ``[cube]`` (on the +y half of the table),
the box centre from ``[target]``; every cube within ``[layout] reach``, ``min_separation``
apart and outside the box, clear of its walls.

**Success.** Every cube's centre inside the box's inner walls and below their top, released
and resting, for ``success.settle_steps`` steps. The reward is the fraction of cubes inside
(1 on success). Failure modes: ``never_grasped``, ``dropped``, ``misplaced`` (carried, left
outside), ``incomplete`` (the moved cubes are in, others never picked), ``timeout``,
``sim_unstable``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from so101_sim.tasks.kind import TaskKind, register_kind
from so101_sim.tasks.layouts import Layout
from so101_sim.tasks.outcomes import Grasp, released
from so101_sim.tasks.props import PROP_FRICTION, add_cube, remove_target_pad

#: Colours of the cubes after the red one (RGBA).
EXTRA_CUBE_RGBA = ((0.95, 0.55, 0.05, 1), (0.55, 0.2, 0.75, 1), (0.1, 0.6, 0.65, 1))
BOX_RGBA = (0.25, 0.45, 0.3, 1)
#: Box-frame slots (m) the expert puts the cubes in, in cube order: >= 8 cm apart and >= 4 cm
#: from the walls, so the opening jaw touches neither a wall nor a cube already placed.
TIDY_SLOTS = ((-0.035, -0.035), (0.035, -0.035), (0.0, 0.035), (0.035, 0.035))


class TidyOutcome:
    def __init__(self) -> None:
        self.settled_steps = 0
        self.grasps: list[Grasp] = []

    def inside(self, env: Any, k: int) -> bool:
        """Cube `k`'s centre is within the box's inner walls and below their top."""
        cube, box = env.cube_pos(k), env.goal_pos()
        return bool(np.all(np.abs(cube[:2] - box[:2]) <= env.task.target_radius)
                    and cube[2] < env.task.wall_height)

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]:
        task = env.task
        n = task.n_cubes
        if not self.grasps:
            self.grasps = [Grasp() for _ in range(n)]
        all_ok, n_inside = True, 0
        for k, g in enumerate(self.grasps):
            _, robot = g.update(env, k, action)
            inside = self.inside(env, k)
            n_inside += inside
            all_ok &= (inside and released(env, k, robot)
                       and env.cube_speed(k) < task.max_speed)
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
            return "misplaced"
        return "incomplete"


@register_kind
class Tidy(TaskKind):
    name = "tidy"
    failure_modes: ClassVar[tuple[str, ...]] = ("never_grasped", "dropped", "misplaced",
                                                "incomplete", "timeout", "sim_unstable")
    max_cubes: ClassVar[int] = len(TIDY_SLOTS)
    place_among_objects: ClassVar[bool] = True

    def acceptable(self, spec: Any, layout: Layout) -> bool:
        if not super().acceptable(spec, layout):
            return False
        margin = spec.target_radius + spec.wall_thickness + spec.cube_size
        return all(not np.all(np.abs(c[:2] - layout.target) < margin) for c in layout.cubes)

    def furnish(self, mjspec: Any, spec: Any) -> None:
        remove_target_pad(mjspec)
        half = spec.cube_size / 2
        for i in range(1, spec.n_cubes):
            add_cube(mjspec, f"cube_{i}", spec.cube_size, spec.cube_mass,
                     EXTRA_CUBE_RGBA[i - 1], [0.1 + 0.05 * i, 0.2, half])
        add_box(mjspec, spec)

    def tracker(self) -> TidyOutcome:
        return TidyOutcome()

    def place(self, spec: Any, env_state: np.ndarray, cube: np.ndarray,
              stage: int) -> tuple[np.ndarray, float]:
        return np.asarray(env_state[7:9]) + TIDY_SLOTS[stage], 0.0


def add_box(mjspec: Any, spec: Any) -> None:
    """An open box on the target's mocap body: floor plate (visual) and four walls that
    collide. Inner half-width = target radius; walls stand 1 mm above the table so the two
    static geoms never touch (no wasted contacts)."""
    import mujoco  # imported by the scene builder already (after the GL backend check)

    target = mjspec.body("target")
    inner, t, h = spec.target_radius, spec.wall_thickness, spec.wall_height
    target.add_geom(name="box_floor", type=mujoco.mjtGeom.mjGEOM_BOX,
                    size=[inner + t, inner + t, 0.0005], pos=[0, 0, 0.0005],
                    rgba=[0.5, 0.62, 0.5, 1], contype=0, conaffinity=0)
    z = 0.001 + h / 2
    for name, pos, size in (
            ("box_wall_px", [inner + t / 2, 0, z], [t / 2, inner + t, h / 2]),
            ("box_wall_nx", [-inner - t / 2, 0, z], [t / 2, inner + t, h / 2]),
            ("box_wall_py", [0, inner + t / 2, z], [inner, t / 2, h / 2]),
            ("box_wall_ny", [0, -inner - t / 2, z], [inner, t / 2, h / 2])):
        target.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=size, pos=pos,
                        rgba=list(BOX_RGBA), contype=1, conaffinity=1, condim=4,
                        friction=list(PROP_FRICTION))
