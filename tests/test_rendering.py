"""GL backend choice, visual fallbacks and task render options."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import mujoco
import pytest

from so101_sim.sim import PickPlaceEnv, scene
from so101_sim.sim.rendering import select_gl_backend
from so101_sim.tasks import load_task


def test_unset_mujoco_gl_picks_a_headless_backend_and_says_which():
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    code = ("from so101_sim.sim.env import PickPlaceEnv\n"
            "env = PickPlaceEnv(image_size=(32, 32)); env.reset(seed=0)\n"
            "import os; print('chosen', os.environ['MUJOCO_GL'])")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=True)
    chosen = proc.stdout.split()[-1]
    assert chosen in ("egl", "osmesa")
    assert f"MUJOCO_GL not set; rendering with {chosen}" in proc.stderr


def test_invalid_mujoco_gl_is_a_clear_error(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "vulkan")
    with pytest.raises(RuntimeError, match=r"MUJOCO_GL='vulkan' is not supported.*'egl'"):
        select_gl_backend()


def test_missing_meshes_fall_back_to_primitive_visuals(monkeypatch, capsys):
    monkeypatch.setattr(scene.meshes, "find_mesh_dir", lambda: None)
    task = dataclasses.replace(load_task(), mesh_grid=0.0123)  # a fresh build_model cache key
    model, visuals = scene.build_model(task, 0.0123)
    assert visuals == "primitive"
    assert model.nmesh == 0
    assert "drawing primitive visuals" in capsys.readouterr().err
    env = PickPlaceEnv(task=task, image_size=(48, 64))
    obs, _ = env.reset(seed=0)
    assert env.visuals == "primitive"
    assert obs["pixels"]["front"].std() > 5
    env.close()


def test_meshes_are_simplified_for_rendering():
    model, visuals = scene.build_model(load_task(), scene.mesh_grid_for(load_task(), 640))
    assert visuals == "mesh" and model.nmesh == 13
    assert model.nmeshface < 40_000  # the official meshes have ~322k triangles
    small = scene.mesh_grid_for(load_task(), 128)
    assert scene.build_model(load_task(), small)[0].nmeshface < model.nmeshface


def test_shadows_and_msaa_are_task_options():
    task = load_task()
    assert task.shadows is False and task.msaa is False
    plain, _ = scene.build_model(task, 0.004)
    fancy, _ = scene.build_model(dataclasses.replace(task, shadows=True, msaa=True), 0.004)
    key = mujoco.mj_name2id(plain, mujoco.mjtObj.mjOBJ_LIGHT, "key")
    assert plain.light_castshadow[key] == 0 and fancy.light_castshadow[key] == 1
    assert plain.vis.quality.offsamples == 0 and fancy.vis.quality.offsamples > 0
    env = PickPlaceEnv(task=dataclasses.replace(task, shadows=True, msaa=True),
                       image_size=(48, 64))
    env.reset(seed=0)
    env.close()
