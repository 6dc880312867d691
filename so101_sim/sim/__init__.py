"""Simulation: the MuJoCo scene of a task, off-screen rendering, and the Gymnasium env.

``SO101Env`` (registered as ``so101_sim/PickPlace-v0``) builds its model from a task spec
(``scene.build_model``: robot and scene MJCF, simplified meshes, the task kind's objects),
renders its cameras with MuJoCo's ``Renderer`` through EGL or OSMesa (``rendering``) and
applies domain randomization (``randomizer``).
"""

from so101_sim.sim.env import (
    CAMERAS,
    ENV_STATE_SIZE,
    FAILURE_MODES,
    IMAGE_SIZE,
    OBS_TYPES,
    PickPlaceEnv,
    SO101Env,
    env_state_size,
)

__all__ = ["CAMERAS", "ENV_STATE_SIZE", "FAILURE_MODES", "IMAGE_SIZE", "OBS_TYPES", "PickPlaceEnv",
           "SO101Env", "env_state_size"]
