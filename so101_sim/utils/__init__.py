"""Utilities under the whole pipeline: data folders, LeRobot units, devices and CPU count,
checkpoint trust checks, video-backend notes and the image resize shared by training and
evaluation. Nothing here imports another part of so101_sim."""

from so101_sim.utils.devices import cpu_count
from so101_sim.utils.paths import assets_dir, envs_dir, policy_dir, shipped_policy_dir
from so101_sim.utils.units import FEATURE_NAMES, MOTOR_NAMES, lerobot_to_radians, radians_to_lerobot

__all__ = ["FEATURE_NAMES", "MOTOR_NAMES", "assets_dir", "cpu_count", "envs_dir",
           "lerobot_to_radians", "policy_dir", "radians_to_lerobot", "shipped_policy_dir"]
