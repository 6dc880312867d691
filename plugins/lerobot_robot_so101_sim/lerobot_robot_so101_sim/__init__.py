"""Imported by lerobot at start-up (its distribution name starts with ``lerobot_robot_``):
registers ``--robot.type=so101_sim`` and ``--teleop.type=so101_sim_expert``. lerobot finds the
device classes here, in the package of their configs (``make_device_from_device_class``)."""

from lerobot_robot_so101_sim.config import (
    ROBOT_TYPE,
    TELEOP_TYPE,
    SO101SimConfig,
    SO101SimExpertConfig,
)
from lerobot_robot_so101_sim.registry import connected_robot
from lerobot_robot_so101_sim.robot import SO101Sim
from lerobot_robot_so101_sim.teleoperator import SO101SimExpert

__all__ = ["ROBOT_TYPE", "TELEOP_TYPE", "SO101Sim", "SO101SimConfig", "SO101SimExpert",
           "SO101SimExpertConfig", "connected_robot"]
