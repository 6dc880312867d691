"""What one eval env worker costs per action chunk, alone on one core, for each render path.

    .venv/bin/python benchmarks/bench_worker.py [--chunks 150] [--repeats 3]

Each row builds the worker `so101-sim eval` would build (``EnvWorkerConfig``: the pick_place
task, front and side cameras, To=2, chunks of Ta=8 steps) in a child process pinned to one
core, runs `--chunks` chunks from a few reset seeds with the arm held at its start pose, and
reports CPU ms per chunk (the child's and its finished children's, so a video's ffmpeg
counts), split into physics and render time as the worker's replies report them. A chunk
renders the two frames the policy reads (its last two steps); a filmed episode renders every
step and encodes it too, so that row shows what a video adds. Rows run in rounds, in turn, so
the machine's drift hits all alike; medians are printed. In a real eval 16 workers and the
policy's forwards share the cores, so each costs more there.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

#: (label, render size, mesh width (None: the render's own), resize to, filmed)
ROWS = [
    ("default: 180x240, recorded 640 px meshes, resized to 60x80", (180, 240), 640, (60, 80),
     False),
    ("240x320, 640 px meshes (the default before 2026-12-05)", (240, 320), 640, (60, 80),
     False),
    ("--faithful: 480x640, 640 px meshes, resized to 60x80", (480, 640), 640, (60, 80), False),
    ("direct: 60x80 (`--image-size 60x80`), 80 px meshes", (60, 80), None, None, False),
    ("60x80 renders with the recorded 640 px meshes", (60, 80), 640, None, False),
    ("direct 60x80, filmed (every step rendered and encoded)", (60, 80), None, None, True),
]

CHILD = r"""
import json, os, resource, sys, time
import numpy as np
from so101_sim.harness.env_worker import EnvWorkerConfig
from so101_sim.harness.frames import with_cameras
from so101_sim.tasks import load_task
size, mesh, resize, film, chunks, core = json.loads(sys.argv[1])
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {core})
cams = ("front", "side")
cfg = EnvWorkerConfig(task=with_cameras(load_task("pick_place"), cams),
                      render_size=tuple(size), cameras=cams, env_state=False, n_obs_steps=2,
                      mesh_width=mesh, resize_to=tuple(resize) if resize else None)
worker = cfg()
worker.reset(100000, False)  # builds the GL context and uploads the meshes: not timed
def cpu():  # this process and its finished children (the video's ffmpeg)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + kids.ru_utime + kids.ru_stime
phys = rend = 0.0
t0 = cpu()
for k in range(chunks):
    if k % 25 == 0:  # a new episode every 200 steps, as in an eval
        reply = worker.reset(100001 + k // 25, film)
    else:
        reply = worker.act(np.tile(worker.env.agent_pos(), (8, 1)).astype(np.float32))
    phys += reply["physics_s"]
    rend += reply["render_s"]
worker.close()  # ends the last filmed episode's encoder, so its CPU is counted
print(json.dumps({"cpu": (cpu() - t0) / chunks, "physics": phys / chunks,
                  "render": rend / chunks}))
"""


def _run(row: tuple, chunks: int, core: int) -> dict[str, float]:
    _, size, mesh, resize, film = row
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    env.setdefault("PYOPENGL_PLATFORM", env["MUJOCO_GL"])
    cmd = [sys.executable, "-c", CHILD, json.dumps([size, mesh, resize, film, chunks, core])]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"worker child failed for {row[0]!r}:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--chunks", type=int, default=150, help="chunks timed per row and round")
    p.add_argument("--repeats", type=int, default=3, help="rounds over the rows")
    p.add_argument("--core", type=int, default=0, help="CPU core to pin the children to")
    args = p.parse_args(argv)
    if args.chunks < 1 or args.repeats < 1:
        p.error(f"--chunks {args.chunks} and --repeats {args.repeats} must both be >= 1")
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [0]
    if args.core not in cores:
        p.error(f"--core {args.core} is not a core this process may use; give one of {cores}")
    results: dict[str, list[dict[str, float]]] = {r[0]: [] for r in ROWS}
    for _ in range(args.repeats):
        for row in ROWS:
            results[row[0]].append(_run(row, args.chunks, args.core))
    base = statistics.median(r["cpu"] for r in results[ROWS[0][0]])
    print(f"one env worker on one core, {args.chunks} chunks of 8 steps, medians of "
          f"{args.repeats} rounds\n")
    print("| worker | CPU ms per chunk | physics ms | render ms | vs default |")
    print("|---|---|---|---|---|")
    for label, runs in results.items():
        med = {k: 1e3 * statistics.median(r[k] for r in runs) for k in runs[0]}
        print(f"| {label} | {med['cpu']:.2f} | {med['physics']:.2f} | {med['render']:.2f} | "
              f"{med['cpu'] / (1e3 * base):.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
