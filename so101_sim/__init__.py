"""so101-sim: a MuJoCo SO-101 pick-and-place suite for LeRobot users.

Importing the package registers the Gymnasium env ``so101_sim/PickPlace-v0``; it loads only
mujoco, numpy and gymnasium (torch and lerobot load in the modules that need them).
"""

from gymnasium.envs.registration import register, registry

from so101_sim.utils.video_backend import quiet_pyav_fallback

__version__ = "0.1.0"
ENV_ID = "so101_sim/PickPlace-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="so101_sim.sim.env:SO101Env", max_episode_steps=None,
             disable_env_checker=True)

# No FFmpeg shared libraries: one line from us instead of lerobot's 100-line torchcodec traceback
quiet_pyav_fallback()

__all__ = ["ENV_ID", "__version__"]
