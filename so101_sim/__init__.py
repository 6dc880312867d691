"""so101-sim: a MuJoCo SO-101 pick-and-place suite for LeRobot users.

Importing the package registers the Gymnasium env ``so101_sim/PickPlace-v0`` (any task by its
``task=`` argument) and one id per task of ``envs/`` (``so101_sim/Stack-v0`` is
``task="stack"``); it loads only mujoco, numpy and gymnasium (torch and lerobot load in the
modules that need them).
"""

from gymnasium.envs.registration import register, registry

from so101_sim.utils.paths import envs_dir
from so101_sim.utils.video_backend import quiet_pyav_fallback

__version__ = "0.1.0"
ENV_ID = "so101_sim/PickPlace-v0"


def task_env_id(task: str) -> str:
    """The Gymnasium id of a task of ``envs/``, e.g. ``pick_place_dr`` ->
    ``so101_sim/PickPlaceDr-v0``."""
    return f"so101_sim/{''.join(w.capitalize() for w in task.split('_'))}-v0"


# The env truncates its own episodes (the task's max_steps), hence no TimeLimit wrapper.
if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="so101_sim.sim.env:SO101Env", max_episode_steps=None,
             disable_env_checker=True)
TASK_ENV_IDS = {p.stem: task_env_id(p.stem) for p in sorted(envs_dir().glob("*.toml"))}
for _task, _id in TASK_ENV_IDS.items():
    if _id not in registry and _id != ENV_ID:
        register(id=_id, entry_point="so101_sim.sim.env:SO101Env", max_episode_steps=None,
                 disable_env_checker=True, kwargs={"task": _task})

# No FFmpeg shared libraries: one line from us instead of lerobot's 100-line torchcodec traceback
quiet_pyav_fallback()

__all__ = ["ENV_ID", "TASK_ENV_IDS", "__version__", "task_env_id"]
