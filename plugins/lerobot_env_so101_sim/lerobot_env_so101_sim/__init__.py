"""Imported by lerobot at start-up (its name starts with ``lerobot_env_``); registers the
``so101_pick_place`` env type by importing ``so101_sim.lerobot_plugin``."""

from so101_sim.lerobot_plugin import ENV_TYPE, SO101PickPlaceEnvConfig

__all__ = ["ENV_TYPE", "SO101PickPlaceEnvConfig"]
