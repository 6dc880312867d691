"""What the Ray backend costs on one node: eval and record, local backend vs Ray, side by side.

    taskset -c 1 .venv/bin/python benchmarks/bench_cluster.py            # ~10 minutes
    taskset -c 1 .venv/bin/python benchmarks/bench_cluster.py --quick    # a sanity run

Every row runs in its own child process, one after the other in one run: the scripted
expert's episodes/s (state only: no rendering, so the per-call overhead shows most), the
shipped diffusion policy's episodes/s (forwards batched in the driver, frames rendered in the
workers and sent to the driver), and ``record``'s frames/s (env-steps/s; workers encode whole
episodes and send the mp4s back). Each with ``--backend local`` and ``--backend ray`` (a
local Ray runtime started in the child, timed separately: a driver that joins a running
cluster with ``--ray-address auto`` does not pay it). "wall" includes starting the workers
(processes or actors) and everything after; rates are per wall second. Run it pinned to one
core as above and the numbers are one-core numbers (both backends share that core).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "policy" / "pick_place_diffusion"
TAG = "BENCH_RESULT "


def child_main(job: dict[str, Any]) -> None:
    """Run one configuration and print its numbers as a tagged JSON line."""
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    import lerobot.datasets.lerobot_dataset  # noqa: F401  (a fixed import cost, not timed)

    runtime_s = 0.0
    if job["backend"] == "ray":
        import ray

        from so101_sim.utils.devices import cpu_count

        t = time.perf_counter()
        ray.init(address="local", num_cpus=cpu_count(), include_dashboard=False,
                 logging_level="ERROR")
        runtime_s = time.perf_counter() - t
    out = Path(job["out"])
    if job["kind"] == "record":
        from so101_sim.record import record

        t = time.perf_counter()
        s = record(out, job["episodes"], image_size=tuple(job["image_size"]),
                   workers=job["workers"], backend=job["backend"], progress=False)
        wall = time.perf_counter() - t
        result = {"count": s["env_steps"], "unit": "frames/s", "episodes": s["episodes"],
                  "start_s": s["worker_start_s"]}
    else:
        from so101_sim.harness import evaluate, load_policy

        policy = load_policy(job["policy"]) if job["policy"] != "expert" else "expert"
        t = time.perf_counter()
        r = evaluate(policy, episodes=job["episodes"], n_envs=job["workers"], videos=0,
                     out_dir=out, backend=job["backend"], progress=False, report=False,
                     log=lambda _: None)
        wall = time.perf_counter() - t
        agg = r["aggregated"]
        result = {"count": job["episodes"], "unit": "episodes/s", "episodes": job["episodes"],
                  "success": agg["n_success"], "start_s": r["config"]["workers"]["start_s"],
                  "shas": [e["actions_sha"] for e in r["per_episode"]]}
    print(TAG + json.dumps({**job, **result, "wall_s": wall, "runtime_s": runtime_s,
                            "cpu_s": time.process_time()}), flush=True)


def run(job: dict[str, Any], timeout: float) -> dict[str, Any]:
    proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(job)],
                          capture_output=True, text=True, timeout=timeout)
    for line in proc.stdout.splitlines():
        if line.startswith(TAG):
            return json.loads(line[len(TAG):])
    raise RuntimeError(f"{job['name']} / {job['backend']} failed (exit {proc.returncode}):\n"
                       f"{proc.stderr[-3000:]}")


def main() -> None:
    if len(sys.argv) >= 3 and sys.argv[1] == "--child":
        child_main(json.loads(sys.argv[2]))
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--expert-episodes", type=int, default=16)
    p.add_argument("--policy-episodes", type=int, default=8)
    p.add_argument("--record-episodes", type=int, default=4)
    p.add_argument("--workers", type=int, default=2, help="env workers / actors per run")
    p.add_argument("--record-size", default="240x320", help="HEIGHTxWIDTH per camera")
    p.add_argument("--policy", default=str(SHIPPED), help="checkpoint for the policy rows")
    p.add_argument("--quick", action="store_true", help="few episodes, small frames")
    p.add_argument("--json", type=Path, default=None, help="also write raw results here")
    args = p.parse_args()
    if args.quick:
        args.expert_episodes, args.policy_episodes, args.record_episodes = 4, 2, 1
        args.record_size = "96x128"
    h, w = (int(v) for v in args.record_size.split("x"))
    cores = len(os.sched_getaffinity(0))
    load = os.getloadavg()
    print(f"bench_cluster: {cores} CPU(s) in this process's affinity; load average "
          f"{load[0]:.2f}; {args.workers} workers per run", flush=True)
    workloads = [("expert eval", "eval", "expert", args.expert_episodes)]
    if Path(args.policy, "model.safetensors").exists():
        workloads.append(("shipped policy eval", "eval", args.policy, args.policy_episodes))
    workloads.append((f"record {h}x{w}", "record", None, args.record_episodes))
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_cluster_") as tmp:
        for name, kind, policy, episodes in workloads:
            for backend in ("local", "ray"):
                job = {"name": name, "kind": kind, "policy": policy, "episodes": episodes,
                       "backend": backend, "workers": args.workers, "image_size": [h, w],
                       "out": str(Path(tmp) / f"{kind}-{backend}-{len(rows)}")}
                r = run(job, timeout=1800)
                rows.append(r)
                print(f"  {name} / {backend}: {r['count'] / r['wall_s']:.2f} {r['unit']} "
                      f"(wall {r['wall_s']:.1f} s, runtime start {r['runtime_s']:.1f} s)",
                      flush=True)
    print()
    print("| workload | backend | count | Ray runtime start s | workers start s | wall s | "
          "rate | Ray vs local | rate after start | Ray vs local after start |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for i, r in enumerate(rows):
        rate = r["count"] / r["wall_s"]
        steady = r["count"] / max(r["wall_s"] - r["start_s"], 1e-9)
        base, base_steady = rate, steady
        if r["backend"] == "ray":
            b = rows[i - 1]
            base, base_steady = b["count"] / b["wall_s"], b["count"] / (b["wall_s"] - b["start_s"])
        same = ""
        if r["backend"] == "ray" and "shas" in r:
            same = ", same results" if r["shas"] == rows[i - 1]["shas"] else ", RESULTS DIFFER"
        print(f"| {r['name']} | {r['backend']} | {r['count']} {r['unit'].split('/')[0]} | "
              f"{r['runtime_s']:.1f} | {r['start_s']:.1f} | {r['wall_s']:.1f} | "
              f"{rate:.2f} {r['unit']} | {rate / base:.2f}x{same} | {steady:.2f} | "
              f"{steady / base_steady:.2f}x |")
    load = os.getloadavg()
    print(f"\nload average at the end {load[0]:.2f}; {cores} CPU(s); wall includes starting "
          "the workers; the Ray runtime start is paid once per driver that starts one "
          "(not when joining a cluster with --ray-address)")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
