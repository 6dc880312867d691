"""Where an episode's objects start: drawn from the reset seed by the task's ranges.

Every kind draws the same way by default (``TaskKind.draw``): each cube's (x, y, yaw) from the
``[cube]`` ranges, the goal's (x, y) from the ``[target]`` ranges, and the whole draw is
repeated until it satisfies ``[layout]``: every object within ``reach`` of the arm's pan axis
and every pair at least ``min_separation`` apart. The helpers here are those rules.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from so101_sim.tasks import TaskSpec

PAN_AXIS_XY = (0.0388353, 0.0)  # shoulder_pan axis in the world (body `shoulder`, so101.xml)
MAX_DRAWS = 1000  # redraws before a layout rule is declared unsatisfiable


@dataclass
class Layout:
    """Start of an episode: ``cubes`` (n, 3) x, y, yaw_deg of every free cube in
    ``TaskKind.cube_names`` order; ``target`` (2,) x, y of the goal."""

    cubes: np.ndarray
    target: np.ndarray


def draw_cubes(spec: TaskSpec, rng: np.random.Generator) -> list[list[float]]:
    """(x, y, yaw_deg) of each of the task's cubes from the ``[cube]`` ranges."""
    return [[rng.uniform(*spec.cube_x), rng.uniform(*spec.cube_y), rng.uniform(*spec.cube_yaw)]
            for _ in range(spec.n_cubes)]


def reach_radius(point: Sequence[float]) -> float:
    """Distance of an (x, y) point from the arm's pan axis (m)."""
    return float(np.hypot(point[0] - PAN_AXIS_XY[0], point[1] - PAN_AXIS_XY[1]))


def in_reach(spec: TaskSpec, points: Sequence[np.ndarray]) -> bool:
    if spec.reach is None:
        return True
    lo, hi = spec.reach
    return all(lo <= reach_radius(p) <= hi for p in points)


def all_separated(spec: TaskSpec, points: Sequence[np.ndarray]) -> bool:
    if spec.min_separation <= 0:
        return True
    return all(np.linalg.norm(points[i] - points[j]) >= spec.min_separation
               for i in range(len(points)) for j in range(i + 1, len(points)))
