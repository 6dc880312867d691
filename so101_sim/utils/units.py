"""Conversions between LeRobot's SO-101 units and the MJCF's joint radians.

LeRobot (0.6.x, "new calibration"): the five arm joints in degrees with 0 at the middle of the
joint's range, which is also the MJCF's zero, so degrees = radians * 180 / pi; the gripper in
0 (closed) .. 100 (open), mapped linearly onto the gripper joint's range.
"""

from __future__ import annotations

import numpy as np

ARM_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
MOTOR_NAMES = (*ARM_JOINTS, "gripper")
FEATURE_NAMES = tuple(f"{name}.pos" for name in MOTOR_NAMES)
GRIPPER_RANGE_RAD = (-0.174533, 1.7453292)
_G_LO, _G_HI = GRIPPER_RANGE_RAD


def lerobot_to_radians(values: np.ndarray) -> np.ndarray:
    """[..., 6] LeRobot units -> [..., 6] joint radians (float64)."""
    v = np.asarray(values, dtype=np.float64)
    out = np.deg2rad(v)
    out[..., 5] = _G_LO + v[..., 5] / 100.0 * (_G_HI - _G_LO)
    return out


def radians_to_lerobot(q: np.ndarray) -> np.ndarray:
    """[..., 6] joint radians -> [..., 6] LeRobot units (float64)."""
    q = np.asarray(q, dtype=np.float64)
    out = np.rad2deg(q)
    out[..., 5] = (q[..., 5] - _G_LO) / (_G_HI - _G_LO) * 100.0
    return out
