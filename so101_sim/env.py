"""Deprecated: the env moved to ``so101_sim.sim`` (kept for one release; import from there)."""

import warnings

from so101_sim.sim.env import (
    CAMERAS,
    ENV_STATE_SIZE,
    FAILURE_MODES,
    OBS_TYPES,
    PickPlaceEnv,
    SO101Env,
    env_state_size,
)

warnings.warn("so101_sim.env is deprecated and will be removed in the next release; import "
              "SO101Env and friends from so101_sim.sim", DeprecationWarning, stacklevel=2)

__all__ = ["CAMERAS", "ENV_STATE_SIZE", "FAILURE_MODES", "OBS_TYPES", "PickPlaceEnv", "SO101Env",
           "env_state_size"]
