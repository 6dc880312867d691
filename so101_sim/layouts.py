"""Where an episode's objects start: drawn from the reset seed by the task's ranges.

Every task draws the same way: each cube's (x, y, yaw) from the ``[cube]`` ranges, the goal's
(x, y) from the ``[target]`` ranges (the target pad, stack's blue base cube, tidy's box), and
the whole draw is repeated until it satisfies ``[layout]``: every object within ``reach``
of the arm's pan axis and every pair at least ``min_separation`` apart (tidy: every cube also
outside the box). The first draw of ``pick_place`` always passes, so its random stream is
the one it has always been.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from so101_sim.task import TaskSpec

PAN_AXIS_XY = (0.0388353, 0.0)  # shoulder_pan axis in the world (body `shoulder`, so101.xml)
MAX_DRAWS = 1000  # redraws before a layout rule is declared unsatisfiable


@dataclass
class Layout:
    """Start of an episode: ``cubes`` (n, 3) x, y, yaw_deg of every free cube in
    ``scene.cube_names`` order; ``target`` (2,) x, y of the goal."""

    cubes: np.ndarray
    target: np.ndarray


def _draw(task: TaskSpec, rng: np.random.Generator) -> Layout:
    cubes = [[rng.uniform(*task.cube_x), rng.uniform(*task.cube_y), rng.uniform(*task.cube_yaw)]
             for _ in range(task.n_cubes)]
    target = np.array([rng.uniform(*task.target_x), rng.uniform(*task.target_y)])
    if task.kind == "lift":
        target = np.array(cubes[0][:2])  # the lift point is above the cube's start
    if task.kind == "stack":  # the blue base cube stands on the target spot
        cubes.append([target[0], target[1], rng.uniform(*task.cube_yaw)])
    return Layout(np.array(cubes, dtype=np.float64), target)


def _acceptable(task: TaskSpec, layout: Layout) -> bool:
    points = [c[:2] for c in layout.cubes]
    if task.kind in ("pick_place", "tidy"):
        points.append(layout.target)
    if task.reach is not None:
        lo, hi = task.reach
        for p in points:
            r = float(np.hypot(p[0] - PAN_AXIS_XY[0], p[1] - PAN_AXIS_XY[1]))
            if not lo <= r <= hi:
                return False
    if task.min_separation > 0:
        for i in range(len(points)):
            for j in range(i + 1, len(points)):
                if np.linalg.norm(points[i] - points[j]) < task.min_separation:
                    return False
    if task.kind == "tidy":  # cubes start outside the box, clear of its walls
        margin = task.target_radius + task.wall_thickness + task.cube_size
        for c in layout.cubes:
            if np.all(np.abs(c[:2] - layout.target) < margin):
                return False
    return True


def sample_layout(task: TaskSpec, rng: np.random.Generator) -> Layout:
    """Draw the objects' start from `rng` (redrawn until the layout rules hold)."""
    for _ in range(MAX_DRAWS):
        layout = _draw(task, rng)
        if _acceptable(task, layout):
            return layout
    raise ValueError(f"{task.source or task.name}: no layout satisfies the task's rules in "
                     f"{MAX_DRAWS} draws (cube x {list(task.cube_x)}, y {list(task.cube_y)}; "
                     f"target x {list(task.target_x)}, y {list(task.target_y)}; reach "
                     f"{task.reach}; min_separation {task.min_separation}); widen the ranges "
                     "or relax [layout]")
