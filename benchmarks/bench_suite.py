"""Rendering cost of the suite's options: domain randomization on vs off, 3 cameras vs 2.

    taskset -c 1 .venv/bin/python benchmarks/bench_suite.py [--seconds 10] [--rounds 3]

Env steps/s of ``pick_place`` (DR off) and ``pick_place_dr`` (DR on), and of ``pick_place``
with cameras front+side and front+side+wrist, each at 96x128 and 480x640, measured in one run:
every configuration runs in its own child process (its own GL context) pinned to the same core,
and the configurations alternate for ``--rounds`` rounds so that a change in machine load hits
them alike; the best round of each is reported, as steps per CPU-second of the child (what an
unshared core would give; wall-clock steps/s beside it). Steps follow a fixed joint-space sweep
around the rest pose and the env resets (with the next seed) every 300 steps, so the
per-episode randomization cost is included. Target: DR on within 15% of off. Prints markdown.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

RESULT_TAG = "BENCH_RESULT "
EPISODE = 300
REST = (-10.374, -81.670, 77.846, 2.681, 123.209, 6.495)
SIZES = ((96, 128), (480, 640))
TARGET_DR = 0.85  # DR on must keep at least this fraction of the steps/s without it


def child(job: dict[str, Any]) -> dict[str, Any]:
    """Step one env configuration for `job["seconds"]` after a warm-up; report steps/s."""
    import numpy as np

    from so101_sim.sim import SO101Env

    env = SO101Env(job["task"], image_size=tuple(job["size"]), cameras=tuple(job["cameras"]))
    actions = []
    for i in range(EPISODE):
        a = np.array(REST)
        a[:4] += 10.0 * np.sin(2 * np.pi * np.array([0.25, 0.2, 0.3, 0.35]) * i / 30)
        actions.append(a.astype(np.float32))
    seed, k = 0, 0
    env.reset(seed=seed)

    def step() -> None:
        nonlocal seed, k
        env.step(actions[k])
        k += 1
        if k >= EPISODE:
            seed, k = seed + 1, 0
            env.reset(seed=seed)

    for _ in range(30):
        step()
    env.time_render = env.time_physics = 0.0
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < job["seconds"] or n < 50:
        step()
        n += 1
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    env.close()
    return {"steps": n, "wall": wall, "cpu": cpu, "render": env.time_render,
            "physics": env.time_physics}


def run_child(job: dict[str, Any], core: int | None) -> dict[str, Any]:
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
           "OMP_NUM_THREADS": "1"}
    pin = (lambda: os.sched_setaffinity(0, {core})) if core is not None else None
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child",
                           json.dumps(job)], env=env, capture_output=True, text=True,
                          preexec_fn=pin, timeout=job["seconds"] * 5 + 240)
    for line in proc.stdout.splitlines():
        if line.startswith(RESULT_TAG):
            return json.loads(line[len(RESULT_TAG):])
    raise RuntimeError(f"child {job} failed: {(proc.stderr or proc.stdout)[-2000:]}")


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        print(RESULT_TAG + json.dumps(child(json.loads(sys.argv[2]))), flush=True)
        return
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=10.0, help="timed seconds per config")
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds (best is kept)")
    p.add_argument("--core", type=int, default=None,
                   help="pin children to this core (default: this process's own CPU set)")
    args = p.parse_args()

    configs = []
    for h, w in SIZES:
        for label, task, cams in (("DR off", "pick_place", ("front", "side")),
                                  ("DR on", "pick_place_dr", ("front", "side")),
                                  ("3 cameras", "pick_place", ("front", "side", "wrist"))):
            configs.append({"label": label, "task": task, "size": [h, w], "cameras": cams,
                            "seconds": args.seconds})
    best: dict[tuple[str, tuple[int, int]], dict[str, Any]] = {}
    t_start = time.perf_counter()
    for r in range(args.rounds):
        for job in configs:
            key = (job["label"], tuple(job["size"]))
            res = run_child(job, args.core)
            res["sps"] = res["steps"] / res["wall"]
            res["spc"] = res["steps"] / res["cpu"]  # per CPU-second: fair on a shared core
            print(f"round {r + 1}: {job['label']:>9} {key[1][0]}x{key[1][1]}: "
                  f"{res['spc']:,.1f} steps/CPU-s, {res['sps']:,.1f} steps/s (cpu "
                  f"{100 * res['cpu'] / res['wall']:.0f}%)", flush=True)
            if key not in best or res["spc"] > best[key]["spc"]:
                best[key] = res

    print(f"\nbench_suite: {args.rounds} rounds x {len(configs)} configs, {args.seconds:g} s "
          f"each, core {args.core if args.core is not None else sorted(os.sched_getaffinity(0))}"
          f", load avg {os.getloadavg()[0]:.2f}, {time.perf_counter() - t_start:.0f} s total\n")
    print("Env steps per CPU-second of the child (its wall-clock rate in brackets; the core "
          "may be shared, so the ratios use CPU time):\n")
    print("| image size | DR off (pick_place) | DR on (pick_place_dr) | on/off | "
          "2 cameras (= DR off) | 3 cameras (+wrist) | 3/2 |")
    print("|---|---|---|---|---|---|---|")

    def rate(r: dict[str, Any]) -> str:
        return f"{r['spc']:,.1f} ({r['sps']:,.1f})"

    for size in SIZES:
        off, on, three = (best[(k, size)] for k in ("DR off", "DR on", "3 cameras"))
        ratio = on["spc"] / off["spc"]
        verdict = "PASS" if ratio >= TARGET_DR else "FAIL"
        print(f"| {size[0]}x{size[1]} | {rate(off)} | {rate(on)} | {ratio:.2f} ({verdict}, "
              f"target >= {TARGET_DR:.2f}) | {rate(off)} | {rate(three)} | "
              f"{three['spc'] / off['spc']:.2f} |")
    print("\nms per step (render / physics / other):")
    for (label, size), res in sorted(best.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        n = res["steps"]
        other = res["wall"] - res["render"] - res["physics"]
        print(f"- {label} {size[0]}x{size[1]}: {1000 * res['render'] / n:.2f} / "
              f"{1000 * res['physics'] / n:.2f} / {1000 * other / n:.2f}")


if __name__ == "__main__":
    main()
