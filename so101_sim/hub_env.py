"""SO-101 pick-and-place from so101-sim as a LeRobot Hub env: push this file, unchanged, as
``env.py`` to your own Hub repo, then anyone with so101-sim installed can build it with::

    from lerobot.envs.factory import make_env
    envs = make_env("<you>/<repo>", n_envs=8, trust_remote_code=True)  # {suite: {0: VectorEnv}}

It holds no simulation code (that stays in the so101-sim package, versioned and tested): it
builds the same env as ``--env.type=so101_pick_place``. The settings below are read from the
environment (``SO101_TASK=stack``, ``SO101_IMAGE_SIZE=60x80``), so one pushed file serves
every task and image size. Find this file with
``python -c "import so101_sim.hub_env as m; print(m.__file__)"``.
"""

from __future__ import annotations

import os
from typing import Any

try:
    from so101_sim.lerobot_plugin import SO101PickPlaceEnvConfig
except ModuleNotFoundError as exc:  # lerobot's loader reports the missing module by name
    raise ModuleNotFoundError(
        f"this Hub env runs so101-sim's simulation, which is not installed here ({exc}); "
        "install it (pip install so101-sim, or from its repository) and load again",
        name="so101_sim") from exc

TASK = os.environ.get("SO101_TASK", "pick_place")  # a task of the suite, or a TOML path
IMAGE_SIZE = os.environ.get("SO101_IMAGE_SIZE", "480x640")  # HEIGHTxWIDTH of both cameras
OBS_TYPE = os.environ.get("SO101_OBS_TYPE", "pixels_agent_pos")


def make_env(n_envs: int = 1, use_async_envs: bool = False, cfg: Any = None) -> dict:
    """``{"so101_pick_place": {0: VectorEnv}}`` with `n_envs` envs, as lerobot's hub loader
    expects; `cfg` (an EnvConfig lerobot may pass) overrides task and image size."""
    try:
        h, w = (int(v) for v in IMAGE_SIZE.lower().split("x"))
    except ValueError:
        raise ValueError(f"SO101_IMAGE_SIZE={IMAGE_SIZE!r} is invalid; expected HEIGHTxWIDTH, "
                         "e.g. 480x640") from None
    task = getattr(cfg, "task", None) or TASK
    h = getattr(cfg, "image_height", None) or h
    w = getattr(cfg, "image_width", None) or w
    config = SO101PickPlaceEnvConfig(task=task, image_height=h, image_width=w, obs_type=OBS_TYPE)
    return config.create_envs(n_envs=n_envs, use_async_envs=use_async_envs)
