"""Where a task may put its objects: on the table, clear of the base, where the expert reaches.

A task file whose cube or target range lies off the table or out of the arm's reach loads
fine and then fails every episode (or every layout draw); ``check_ranges`` refuses it when the
file loads, naming the key, its value and the range allowed. No MuJoCo here: the numbers
below come from the scene files and the expert, and ``tests/test_task_ranges.py`` checks them
against the built model and the suite's own task files.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from so101_sim.tasks.layouts import PAN_AXIS_XY

if TYPE_CHECKING:
    from so101_sim.tasks import TaskSpec

#: Table top in world x / y (m): geom `table` of assets/scene_pick_place.xml, centre
#: (0.2, 0), half sizes (0.45, 0.5).
TABLE_X = (-0.25, 0.65)
TABLE_Y = (-0.5, 0.5)
#: The robot's base plate in world x / y (m): geom `base_plate` of assets/so101.xml, centre
#: x 0.005, half sizes (0.045, 0.04). reset(options=...) refuses the same footprint.
BASE_X = (-0.04, 0.05)
BASE_Y = (-0.04, 0.04)
#: Distance from the shoulder_pan axis (m) at which the scripted expert grasps a cube on the
#: table top-down. Far: its IK reaches grasp height with no error out to 0.275 m and misses by
#: 4+ mm from 0.28 m (measured with expert.kinematics.TopDownIK); the suite's tasks go to
#: 0.26 m (pick_place_anywhere). Near: the open jaw (~4.5 cm from the cube's centre) stays
#: clear of the base plate, whose far corner is 0.042 m from the axis; the suite's go to 0.12.
REACH = (0.10, 0.27)
#: The shoulder_pan joint's range (rad, assets/so101.xml): the arm cannot turn further.
PAN_LIMIT = 1.91986


def _corners(xs: tuple[float, float], ys: tuple[float, float]) -> list[tuple[float, float]]:
    return [(x, y) for x in xs for y in ys]


def _radius(x: float, y: float) -> float:
    return math.hypot(x - PAN_AXIS_XY[0], y - PAN_AXIS_XY[1])


def _nearest_radius(xs: tuple[float, float], ys: tuple[float, float]) -> float:
    """Distance from the pan axis to the nearest point of the rectangle xs x ys."""
    cx = min(max(PAN_AXIS_XY[0], xs[0]), xs[1])
    cy = min(max(PAN_AXIS_XY[1], ys[0]), ys[1])
    return _radius(cx, cy)


def _rng(r: tuple[float, float]) -> str:
    return f"[{r[0]:g}, {r[1]:g}]"


def _check_one(name: str, xs: tuple[float, float], ys: tuple[float, float], margin: float,
               reach: tuple[float, float] | None) -> str | None:
    keys = f"{name}.x = {_rng(xs)}, {name}.y = {_rng(ys)}"
    lo_x, hi_x = TABLE_X[0] + margin, TABLE_X[1] - margin
    lo_y, hi_y = TABLE_Y[0] + margin, TABLE_Y[1] - margin
    if not (lo_x <= xs[0] and xs[1] <= hi_x):
        return (f"{name}.x = {_rng(xs)} is off the table; expected within [{lo_x:.3f}, "
                f"{hi_x:.3f}] m (the table top of assets/scene_pick_place.xml, less the "
                "object's half width)")
    if not (lo_y <= ys[0] and ys[1] <= hi_y):
        return (f"{name}.y = {_rng(ys)} is off the table; expected within [{lo_y:.3f}, "
                f"{hi_y:.3f}] m (the table top of assets/scene_pick_place.xml, less the "
                "object's half width)")
    if (xs[0] < BASE_X[1] + margin and xs[1] > BASE_X[0] - margin
            and ys[0] < BASE_Y[1] + margin and ys[1] > BASE_Y[0] - margin):
        return (f"{keys} overlaps the robot's base (x {_rng(BASE_X)}, y {_rng(BASE_Y)} m, "
                "plus the object's half width); expected ranges clear of it, e.g. x >= 0.1")
    near, far = _nearest_radius(xs, ys), max(_radius(x, y) for x, y in _corners(xs, ys))
    if reach is None:  # every point of the ranges may be drawn: all must be reachable
        if near < REACH[0] or far > REACH[1]:
            return (f"{keys} puts the {name} {near:.3f}..{far:.3f} m from the arm's pan axis "
                    f"(x {PAN_AXIS_XY[0]:g}, y 0); expected every point within "
                    f"{REACH[0]:g}..{REACH[1]:g} m (where the scripted expert reaches the "
                    "table top-down), or add [layout] reach to keep draws inside it")
        angle = max(abs(math.atan2(y - PAN_AXIS_XY[1], x - PAN_AXIS_XY[0]))
                    for x, y in _corners(xs, ys))
        if angle > PAN_LIMIT:
            return (f"{keys} reaches {math.degrees(angle):.0f} deg around the pan axis; the "
                    f"arm turns at most {math.degrees(PAN_LIMIT):.0f} deg: keep x larger")
    elif near > reach[1] or far < reach[0]:
        return (f"{keys} is {near:.3f}..{far:.3f} m from the arm's pan axis, never within "
                f"layout.reach = {_rng(reach)}: no layout can be drawn; move the ranges or "
                "widen layout.reach")
    return None


def check_ranges(spec: TaskSpec, has_target: bool = True) -> str | None:
    """Why the cube or target ranges of `spec` cannot be solved, or None. `has_target`: the
    file sets [target] (a kind that has no goal position leaves it out)."""
    if spec.reach is not None:
        lo, hi = spec.reach
        if lo < REACH[0] or hi > REACH[1]:
            return (f"layout.reach = {_rng(spec.reach)} is invalid; expected within "
                    f"{_rng(REACH)} m of the pan axis (where the scripted expert reaches the "
                    "table top-down, clear of the base)")
    half_diagonal = spec.cube_size / 2 * math.sqrt(2)
    problem = _check_one("cube", spec.cube_x, spec.cube_y, half_diagonal, spec.reach)
    if problem is None and has_target:
        problem = _check_one("target", spec.target_x, spec.target_y, 0.0, spec.reach)
    return problem
