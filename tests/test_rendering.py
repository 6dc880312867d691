"""GL backend choice, visual fallbacks and task render options."""

from __future__ import annotations

import dataclasses
import os
import signal
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


def _glfw_without_a_display(monkeypatch) -> None:
    monkeypatch.setenv("MUJOCO_GL", "glfw")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")


def test_glfw_without_a_display_is_one_line_before_any_context(monkeypatch, tmp_path):
    """MUJOCO_GL=glfw over SSH: GLFW warned twice and MuJoCo stopped in MjrContext with "an
    OpenGL platform library has not been loaded", under a traceback; lerobot-eval and the
    lerobot robot the same, from their env workers or connect()."""
    from lerobot_robot_so101_sim import SO101Sim, SO101SimConfig

    from so101_sim.lerobot_plugin import ENV_TYPE, SO101PickPlaceEnvConfig
    from so101_sim.utils.lerobot_cli import TAG

    _glfw_without_a_display(monkeypatch)
    hint = r"MUJOCO_GL='glfw' needs a display and DISPLAY is not set here; .*MUJOCO_GL=egl"
    with pytest.raises(RuntimeError, match=hint):
        select_gl_backend()
    with pytest.raises(RuntimeError, match=hint) as caught:  # lerobot-eval: before the envs
        SO101PickPlaceEnvConfig(image_height=48, image_width=64).create_envs(1)
    assert getattr(caught.value, TAG) == f"--env.type={ENV_TYPE}"  # its one line
    robot = SO101Sim(SO101SimConfig(image_height=48, image_width=64, realtime=False,
                                    calibration_dir=tmp_path / "cal"))
    with pytest.raises(RuntimeError, match=hint) as caught:
        robot.connect()
    assert getattr(caught.value, TAG) == "--robot.type=so101_sim"
    assert not robot.is_connected
    monkeypatch.setenv("DISPLAY", ":0")  # a display named: glfw is tried, not refused
    assert select_gl_backend() == "glfw"


def test_eval_says_glfw_needs_a_display_on_a_line_of_its_own(tmp_path):
    """The line came after eval's progress bar, on the bar's line."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    r = subprocess.run([sys.executable, "-m", "so101_sim", "eval", "--policy", "expert",
                        "--episodes", "1", "--videos", "1", "--out", str(tmp_path / "e")],
                       env={**env, "MUJOCO_GL": "glfw", "HF_HUB_OFFLINE": "1"},
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert any(line.startswith("so101-sim eval: error: MUJOCO_GL='glfw' needs a display and "
                               "DISPLAY is not set") for line in r.stderr.split("\n"))
    assert "ep/s]" not in r.stderr  # no bar was started


def test_a_gl_context_that_fails_is_one_line(tmp_path):
    """MUJOCO_GL=glfw with a DISPLAY that cannot be opened: MuJoCo's FatalError from
    MjrContext becomes one line with the headless backends."""
    env = {**os.environ, "MUJOCO_GL": "glfw", "DISPLAY": ":4242", "HF_HUB_OFFLINE": "1"}
    env.pop("PYOPENGL_PLATFORM", None)
    r = subprocess.run([sys.executable, "-m", "so101_sim", "demo", "--steps", "1", "--out",
                        str(tmp_path / "demo")], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("so101-sim demo: error: MUJOCO_GL='glfw' gave no OpenGL context (")
    assert last.endswith("set MUJOCO_GL=egl or MUJOCO_GL=osmesa, or unset it (so101_sim then "
                         "picks one)")


def test_a_pyopengl_platform_other_than_mujoco_gl_is_one_line(monkeypatch, tmp_path):
    """MUJOCO_GL=egl with PYOPENGL_PLATFORM=osmesa left in the shell for another tool: mujoco.egl
    raised ImportError under a traceback, its message leaving the value out ("is set to {!r}");
    with MUJOCO_GL unset, EGL was picked against the pinned platform and failed the same way."""
    from so101_sim.sim.rendering_probe import probe_backend

    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setenv("PYOPENGL_PLATFORM", "osmesa")
    with pytest.raises(RuntimeError, match=r"^MUJOCO_GL='egl' needs PyOpenGL on egl, but "
                       r"PYOPENGL_PLATFORM='osmesa' is set; unset PYOPENGL_PLATFORM"):
        select_gl_backend()
    monkeypatch.setenv("PYOPENGL_PLATFORM", "EGL")  # the same platform, in any case
    assert select_gl_backend() == "egl"

    monkeypatch.delenv("MUJOCO_GL")  # unset: only the pinned platform can be used
    monkeypatch.setenv("PYOPENGL_PLATFORM", "glx")
    with pytest.raises(RuntimeError, match=r"^headless rendering \(MUJOCO_GL unset\) needs "
                       r"PyOpenGL on egl or osmesa, but PYOPENGL_PLATFORM='glx' is set"):
        select_gl_backend()
    monkeypatch.setenv("PYOPENGL_PLATFORM", "osmesa")
    if probe_backend("osmesa") is None:
        assert select_gl_backend() == "osmesa" == os.environ["MUJOCO_GL"]
    else:  # no OSMesa here (this machine): EGL would work but PyOpenGL is pinned elsewhere
        with pytest.raises(RuntimeError, match=r"^PYOPENGL_PLATFORM='osmesa' \(MUJOCO_GL "
                           r"unset\) leaves only osmesa, which failed here \(.+\); unset "
                           r"PYOPENGL_PLATFORM to let so101_sim try EGL and OSMesa$"):
            select_gl_backend()
        assert "MUJOCO_GL" not in os.environ

    env = {**os.environ, "MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "osmesa",
           "HF_HUB_OFFLINE": "1"}
    r = subprocess.run([sys.executable, "-m", "so101_sim", "demo", "--steps", "1", "--out",
                        str(tmp_path / "demo")], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(
        "so101-sim demo: error: MUJOCO_GL='egl' needs PyOpenGL on egl, but PYOPENGL_PLATFORM=")


def test_a_mujoco_egl_device_id_that_is_no_index_is_named(monkeypatch):
    """MUJOCO_EGL_DEVICE_ID=x: MuJoCo's "invalid literal for int() with base 10: 'x'" named
    no variable (with MUJOCO_GL unset: "EGL failed (ValueError: ...)" among both backends)."""
    said = (r"^MUJOCO_EGL_DEVICE_ID='x' is not a device index; expected an integer from 0 "
            r"\(the first EGL device\), or unset it$")
    monkeypatch.setenv("MUJOCO_EGL_DEVICE_ID", "x")
    monkeypatch.setenv("MUJOCO_GL", "egl")
    with pytest.raises(RuntimeError, match=said):
        select_gl_backend()
    monkeypatch.delenv("MUJOCO_GL")
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    with pytest.raises(RuntimeError, match=said):
        select_gl_backend()
    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setenv("MUJOCO_EGL_DEVICE_ID", "0")  # an index: MuJoCo checks its range
    assert select_gl_backend() == "egl"


_FORK_AFTER_RENDER = """
import multiprocessing as mp
import gymnasium as gym
import so101_sim

def use_inherited(env, q):
    try:
        env.reset(seed=1)
        q.put("rendered")
    except RuntimeError as exc:
        q.put(str(exc))

if __name__ == "__main__":
    env = gym.make("so101_sim/PickPlaceDr-v0", image_size=(32, 32))  # uploads textures too
    env.reset(seed=0)  # EGL's display is open in this process from here on
    try:  # Gymnasium's async envs fork by default
        gym.make_vec("so101_sim/PickPlace-v0", num_envs=2, vectorization_mode="async",
                     image_size=(32, 32)).reset(seed=0)
    except RuntimeError as exc:
        print("MAKE_VEC:", exc)
    q = mp.get_context("fork").SimpleQueue()
    p = mp.get_context("fork").Process(target=use_inherited, args=(env, q))
    p.start(); p.join()
    print("INHERITED:", q.get())
    envs = gym.make_vec("so101_sim/PickPlace-v0", num_envs=2, vectorization_mode="async",
                        vector_kwargs={"context": "forkserver"}, image_size=(32, 32))
    obs, _ = envs.reset(seed=0)
    print("FORKSERVER:", obs["pixels"]["front"].shape)
"""


def test_a_fork_after_an_egl_render_is_refused_with_the_fix_not_a_hang(tmp_path):
    """gym.make_vec(..., vectorization_mode="async") in a process that had rendered: its
    forked workers waited forever in their first frame (Mesa's threads are not copied by
    fork), and so did a forked child using the parent's env."""
    if select_gl_backend() != "egl":
        pytest.skip("EGL only: the refusal is for EGL's state after fork")
    script = tmp_path / "fork_after_render.py"
    script.write_text(_FORK_AFTER_RENDER)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            start_new_session=True)  # a hang leaves no forked worker behind
    try:
        out, err = proc.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"hung: a forked worker waited in its first frame\n{out}\n{err}")
    said = "cannot render in this process: it was forked from process"
    for case in ("MAKE_VEC:", "INHERITED:"):
        line = next((x for x in out.splitlines() if x.startswith(case)), "")
        assert said in line and "vector_kwargs={'context': 'forkserver'}" in line, (out, err)
    assert "FORKSERVER: (2, 32, 32, 3)" in out, (out, err)  # the fix it names works


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
