"""A task kind is one file: a kind registered outside the package loads by name from a task
TOML and is stepped, scored and solved by the scripted expert, with no change to so101_sim."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import shelf_kind  # noqa: F401  (registers kind "shelf", as a user's own package would)

from so101_sim.expert import ScriptedExpert
from so101_sim.sim import SO101Env
from so101_sim.tasks import TaskKind, TaskSpecError, get_kind, load_task, register_kind

REST = np.array([-10.374, -81.670, 77.846, 2.681, 123.209, 6.495], dtype=np.float32)


SHELF_TOML = Path(__file__).with_name("shelf.toml")


def _run(env: SO101Env, policy, seed: int) -> dict:
    obs, _ = env.reset(seed=seed)
    if hasattr(policy, "reset"):
        policy.reset(seed)
    info, done, total = {}, False, 0.0
    while not done:
        action = policy.select_action(obs) if hasattr(policy, "select_action") else policy
        obs, reward, terminated, truncated, info = env.step(action)
        total += reward
        done = terminated or truncated
    return {**info, "return": total}


def test_a_kind_from_outside_the_package_is_solved_by_the_expert():
    spec = load_task(SHELF_TOML)
    assert spec.kind == "shelf" and isinstance(get_kind("shelf"), TaskKind)
    env = SO101Env(spec, obs_type="state")
    assert env.observation_space["environment_state"].shape == (10,)
    assert env.model.geom("shelf").id >= 0  # the kind furnished the scene
    expert = ScriptedExpert(spec, model=env.model)
    for seed in (0, 1, 2):
        info = _run(env, expert, seed)
        assert info["is_success"], (seed, info.get("failure_mode"))
        assert info["failure_mode"] is None and info["return"] == 1.0
        cube, goal = env.cube_pos(0), env.goal_pos()
        assert cube[2] > 0.02  # on the board, not on the table beside it
        assert np.linalg.norm(cube[:2] - goal[:2]) <= spec.target_radius
    env.close()


def test_the_kinds_tracker_scores_a_failure():
    spec = load_task(SHELF_TOML)
    env = SO101Env(spec, obs_type="state")
    env.reset(seed=0)
    for _ in range(spec.max_steps):
        *_, terminated, truncated, info = env.step(REST)
        if terminated or truncated:
            break
    assert truncated and not info["is_success"] and info["failure_mode"] == "never_grasped"
    env.close()


def test_an_unregistered_kind_is_refused_by_name(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(SHELF_TOML.read_text().replace('kind = "shelf"', 'kind = "shelf_v9"'))
    with pytest.raises(TaskSpecError, match=r"kind = 'shelf_v9' is invalid.*register_kind"):
        load_task(path)


def test_register_kind_checks_the_class():
    with pytest.raises(TypeError, match="TaskKind subclass"):
        register_kind(object)
    with pytest.raises(ValueError, match="identifier"):
        register_kind(type("NoName", (TaskKind,), {"name": ""}))
    with pytest.raises(ValueError, match="sim_unstable"):
        register_kind(type("Bad", (TaskKind,), {"name": "bad", "failure_modes": ("dropped",)}))
