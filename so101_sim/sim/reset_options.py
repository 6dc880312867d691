"""Validate `reset(options=...)`: a pinned cube pose or target must be finite, on the table and
clear of the robot's base, or the episode is refused before MuJoCo sees it.

Without this, a NaN pose made MuJoCo reset the state itself mid-step (the arm jumped) and the
episode was reported as `never_grasped`. Bounds are read from the built model (the `table`
and `base_plate` geoms), so a task with another table gets its own limits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from so101_sim.sim.glcheck import mujoco

RESET_OPTIONS = {"cube_pose": "(x, y, yaw_deg)", "target_pos": "(x, y)"}


@dataclass(frozen=True)
class Workspace:
    """Table top and robot-base footprint in world x/y (metres)."""

    x: tuple[float, float]
    y: tuple[float, float]
    base_x: tuple[float, float]
    base_y: tuple[float, float]


def workspace(model: mujoco.MjModel) -> Workspace:
    """The table's and the base plate's x/y extents, from the model's geoms."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)

    def extent(name: str) -> tuple[tuple[float, float], tuple[float, float]]:
        g = model.geom(name).id
        c, h = data.geom_xpos[g], model.geom_size[g]
        return (float(c[0] - h[0]), float(c[0] + h[0])), (float(c[1] - h[1]), float(c[1] + h[1]))

    (tx, ty), (bx, by) = extent("table"), extent("base_plate")
    return Workspace(tx, ty, bx, by)


def _vector(options: dict[str, Any], key: str, n: int) -> np.ndarray:
    raw = options[key]
    try:
        v = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"reset option {key}={raw!r} is not numeric; expected {n} numbers "
                         f"{RESET_OPTIONS[key]}") from None
    if v.shape != (n,):
        raise ValueError(f"reset option {key} has shape {v.shape}; expected ({n},) "
                         f"{RESET_OPTIONS[key]}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"reset option {key}={v.tolist()} contains NaN or inf; expected "
                         f"finite {RESET_OPTIONS[key]} in metres (yaw in degrees)")
    return v


def _check_xy(key: str, xy: np.ndarray, ws: Workspace, margin: float, avoid_base: bool) -> None:
    lo_x, hi_x = ws.x[0] + margin, ws.x[1] - margin
    lo_y, hi_y = ws.y[0] + margin, ws.y[1] - margin
    if not (lo_x <= xy[0] <= hi_x and lo_y <= xy[1] <= hi_y):
        raise ValueError(f"reset option {key} x={xy[0]:g}, y={xy[1]:g} is off the table; "
                         f"expected x in [{lo_x:.3f}, {hi_x:.3f}] and y in [{lo_y:.3f}, "
                         f"{hi_y:.3f}] (metres, world frame)")
    if avoid_base and (ws.base_x[0] - margin < xy[0] < ws.base_x[1] + margin
                       and ws.base_y[0] - margin < xy[1] < ws.base_y[1] + margin):
        raise ValueError(f"reset option {key} x={xy[0]:g}, y={xy[1]:g} is inside the robot's "
                         f"base (x {ws.base_x[0]:.3f}..{ws.base_x[1]:.3f}, y "
                         f"{ws.base_y[0]:.3f}..{ws.base_y[1]:.3f}, plus the cube's half "
                         "diagonal); place it elsewhere on the table, e.g. x=0.2, y=0.05")


def apply_reset_options(options: dict[str, Any] | None, ws: Workspace, cube_size: float,
                        cube: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cube x, y, yaw_deg; target x, y): the drawn values, replaced by valid options."""
    options = options or {}
    unknown = set(options) - set(RESET_OPTIONS)
    if unknown:
        raise ValueError(f"unknown reset options {sorted(unknown)}; expected 'cube_pose' "
                         "(x, y, yaw_deg) and/or 'target_pos' (x, y)")
    if "cube_pose" in options:
        cube = _vector(options, "cube_pose", 3)
        _check_xy("cube_pose", cube, ws, cube_size / 2 * np.sqrt(2), avoid_base=True)
    if "target_pos" in options:
        target = _vector(options, "target_pos", 2)
        _check_xy("target_pos", target, ws, 0.0, avoid_base=True)
    return cube, target
