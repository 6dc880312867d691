"""MjSpec edits task kinds use to furnish the scene: free cubes, and dropping the target pad.

Kinds call these from ``TaskKind.furnish`` before the model is compiled; new elements are
appended after the MJCF's own, so a kind that adds nothing leaves the model unchanged.
``so101_sim.tasks`` imports no mujoco itself: the sim imports it first, after checking
``MUJOCO_GL`` (``so101_sim.sim.glcheck``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import mujoco

PROP_FRICTION = (1, 0.01, 0.001)  # the MJCF's default class "prop" (assets/scene_pick_place.xml)


def add_cube(mjspec: mujoco.MjSpec, name: str, size: float, mass: float,
             rgba: Sequence[float], pos: Sequence[float]) -> None:
    """A free box body `name` (geom and joint of the same name) of edge `size` at `pos`."""
    import mujoco  # imported by the scene builder already (after the GL backend check)

    body = mjspec.worldbody.add_body(name=name, pos=list(pos))
    body.add_freejoint(name=name)
    h = size / 2
    body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[h, h, h], mass=mass,
                  rgba=list(rgba), condim=4, friction=list(PROP_FRICTION))


def remove_target_pad(mjspec: mujoco.MjSpec) -> None:
    """Drop the green pad: the goal is shown by the objects themselves (or not at all)."""
    mjspec.delete(mjspec.geom("target_pad"))
