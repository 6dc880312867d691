"""so101-sim: a MuJoCo SO-101 pick-and-place suite for LeRobot users.

Importing the package registers the Gymnasium env ``so101_sim/PickPlace-v0``; it loads only
mujoco, numpy and gymnasium (torch and lerobot load in the modules that need them).
"""

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"
ENV_ID = "so101_sim/PickPlace-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="so101_sim.env:PickPlaceEnv", max_episode_steps=None,
             disable_env_checker=True)

__all__ = ["ENV_ID", "__version__"]
