"""The sim robots connected in this process, by ``--robot.id``: how the expert teleoperator
finds the robot it drives (lerobot builds the two separately and never introduces them)."""

from __future__ import annotations

import threading
from typing import Any

from lerobot.utils.errors import DeviceAlreadyConnectedError

_CONNECTED: dict[str | None, Any] = {}  # --robot.id (None when not given) -> SO101Sim
_LOCK = threading.Lock()


def add(robot: Any) -> None:
    """Register a connecting robot; a second robot with its id is refused."""
    with _LOCK:
        if robot.id in _CONNECTED:
            raise DeviceAlreadyConnectedError(
                f"an so101_sim robot with --robot.id={robot.id!r} is already connected in "
                "this process; give each sim robot its own --robot.id")
        _CONNECTED[robot.id] = robot


def remove(robot: Any) -> None:
    """Forget a robot (a no-op if another robot now holds its id, or none does)."""
    with _LOCK:
        if _CONNECTED.get(robot.id) is robot:
            del _CONNECTED[robot.id]


def connected_robot(robot_id: str | None = None) -> Any:
    """The connected sim robot with this ``--robot.id``; with None, the only one connected."""
    with _LOCK:
        robots = dict(_CONNECTED)
    if robot_id is not None:
        if robot_id in robots:
            return robots[robot_id]
        raise LookupError(f"no so101_sim robot with --robot.id={robot_id!r} is connected in "
                          f"this process (connected: {_ids(robots)}); pass the robot's id as "
                          "--teleop.robot_id, or leave it out to use the one sim robot")
    if len(robots) == 1:
        return next(iter(robots.values()))
    if not robots:
        raise LookupError("no so101_sim robot is connected in this process: the "
                          "so101_sim_expert teleoperator drives a sim robot of the same "
                          "command; pass --robot.type=so101_sim")
    raise LookupError(f"{len(robots)} so101_sim robots are connected ({_ids(robots)}); pass "
                      "--teleop.robot_id=<the --robot.id to drive>")


def _ids(robots: dict[str | None, Any]) -> str:
    return ", ".join(repr(k) for k in robots) or "none"
