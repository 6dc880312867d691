"""One expert episode as recorded frames, with optional DART noise on the executed actions.

DART noise (``dart_noise > 0``): the env executes the expert's action plus Gaussian noise drawn
from a per-episode stream seeded by the episode seed; ``action`` stays the expert's clean
action (the label) and ``action_executed`` stores what was executed, which ``replay`` uses.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

_DART_STREAM = 0xDA27  # second SeedSequence word: the noise never correlates with the jitter


def check_dart_noise(dart_noise: float) -> float:
    """The noise std as a float, or a ValueError that says what to pass instead."""
    try:
        x = float(dart_noise)
    except (TypeError, ValueError):
        x = math.nan
    if not math.isfinite(x) or x < 0:
        raise ValueError(f"dart_noise={dart_noise!r} is invalid; expected a finite number >= 0 "
                         "(std of the executed-action noise: degrees for the arm joints, "
                         "0..100 units for the gripper); pass e.g. --dart-noise 2, or 0 for none")
    return x


def expert_options(recover: bool = False, grasp_clearance: float | None = None
                   ) -> dict[str, Any]:
    """ScriptedExpert keyword options as stored in the sidecar (defaults left out)."""
    options: dict[str, Any] = {}
    if recover:
        options["recover"] = True
    if grasp_clearance is not None:
        c = float(grasp_clearance)
        if not (math.isfinite(c) and 0.0 <= c <= 0.02):
            raise ValueError(f"grasp_clearance={grasp_clearance!r} is invalid; expected metres "
                             "in [0, 0.02] (the open gripper leaves ~0.025 m around the cube); "
                             "e.g. --grasp-clearance 0.012")
        options["clearance"] = c
    return options


def dart_rng(seed: int) -> np.random.Generator:
    """Noise stream of one episode: fixed by its seed, independent of the expert's jitter."""
    return np.random.default_rng([seed, _DART_STREAM])


def run_episode(env: Any, expert: Any, seed: int, emit: Callable[[dict[str, Any]], None],
                dart_noise: float = 0.0) -> tuple[bool, str | None, int]:
    """Roll the expert for one episode, passing every frame (lerobot's frame dict) to `emit`.

    With `dart_noise`, the env executes ``clip(action + N(0, dart_noise))`` while the frame's
    ``action`` stays the clean expert action; ``action_executed`` holds what was executed.
    The expert follows absolute joint targets, so each clean label also points back from the
    perturbed state to the plan (the DART idea). Returns (success, failure_mode, steps).
    """
    obs, info = env.reset(seed=seed)
    expert.reset(seed)
    rng = dart_rng(seed) if dart_noise > 0 else None
    cube = np.asarray(info["cube_pose"], dtype=np.float32)
    seed_arr = np.array([seed], dtype=np.int64)
    description = env.task.description
    steps, done, step_info = 0, False, {}
    while not done:
        action = np.asarray(expert.select_action(obs), dtype=np.float32)
        executed = action
        frame = {"observation.state": obs["agent_pos"].astype(np.float32), "action": action,
                 "episode_seed": seed_arr, "initial_cube_pose": cube, "task": description}
        if rng is not None:
            noisy = action + rng.normal(0.0, dart_noise, size=action.shape)
            executed = np.clip(noisy, env.action_low, env.action_high).astype(np.float32)
            frame["action_executed"] = executed
        for cam in obs.get("pixels", ()):  # a state-only env gives none (success-rate studies)
            frame[f"observation.images.{cam}"] = obs["pixels"][cam]
        emit(frame)
        obs, _, terminated, truncated, step_info = env.step(executed)
        steps += 1
        done = terminated or truncated
    return bool(step_info.get("is_success", False)), step_info.get("failure_mode"), steps
