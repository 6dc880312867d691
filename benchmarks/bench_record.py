"""End-to-end recording throughput of ``so101-sim record`` with 1 and 2 worker processes.

Usage::

    .venv/bin/python benchmarks/bench_record.py                  # 10 episodes per config
    .venv/bin/python benchmarks/bench_record.py --episodes 20
    .venv/bin/python benchmarks/bench_record.py --quick          # 2 tiny episodes, a sanity run

Each configuration records N scripted-expert episodes (two 480x640 cameras, video encoding,
lerobot's writer) into a fresh temporary dataset, in its own child process, through the same
``record()`` the CLI calls. It prints env-steps/s end to end (worker start-up and finalize
included), the wall time, the time split per step, the CPU time per step, and the time 100
demos would take at that rate. The split is wall time per env step summed over the recording
loops (one per worker): the env's ``time_physics`` / ``time_render`` counters, "encode+write"
(the writer, timed by ``record()``: feeding frames to the video encoders, waiting for them to
finish an episode, lerobot's add_frame/save_episode) and the rest (expert, start-up, waiting).
The encoders run in their own threads, so their CPU shows in "CPU ms/step" (all processes and
threads), which also gives the rate the machine allows when nothing else runs on it.
Targets (issue 3): >= 50 env-steps/s with 2 workers on 2 cores; 100 demos in <= 10 minutes.
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

from so101_sim.cli import parse_image_size

RESULT_TAG = "BENCH_RESULT "
TARGET_STEPS_S = 50.0
TARGET_100_MIN = 10.0


def child_main(job_json: str) -> None:
    """Record one configuration and print its summary as a tagged JSON line."""
    import lerobot.datasets.lerobot_dataset  # noqa: F401  (a fixed import cost, not timed)

    from so101_sim.record import record

    job = json.loads(job_json)
    t0 = time.perf_counter()
    s = record(job["out"], job["episodes"], image_size=tuple(job["image_size"]),
               workers=job["workers"], vcodec=job["vcodec"], dart_noise=job["dart_noise"],
               progress=False)
    s["wall_total"] = time.perf_counter() - t0
    s.pop("failures", None)
    print(RESULT_TAG + json.dumps(s), flush=True)


def run_config(job: dict[str, Any], timeout: float) -> dict[str, Any]:
    """One configuration in a fresh interpreter (no shared GL context or import cache)."""
    proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(job)],
                          capture_output=True, text=True, timeout=timeout)
    for line in proc.stdout.splitlines():
        if line.startswith(RESULT_TAG):
            return json.loads(line[len(RESULT_TAG):])
    raise RuntimeError(f"workers={job['workers']} failed (exit {proc.returncode}):\n"
                       f"{proc.stderr[-3000:]}")


def row(r: dict[str, Any], cores: int) -> str:
    """One markdown table row from a record() summary."""
    steps = max(r["env_steps"], 1)
    ms = {k: 1000 * r[k] / steps
          for k in ("time_physics", "time_render", "time_write", "cpu_seconds")}
    busy = 1000 * r["workers"] * r["seconds"] / steps  # loop-time per step, all workers
    other = busy - ms["time_physics"] - ms["time_render"] - ms["time_write"]
    rate = r["env_steps"] / r["wall_total"]
    per_100 = r["wall_total"] / max(r["new_episodes"], 1) * 100 / 60
    cpu_bound = cores * 1000 / ms["cpu_seconds"]
    ok = "yes" if rate >= TARGET_STEPS_S and per_100 <= TARGET_100_MIN else "no"
    return (f"| {r['workers']} | {r['new_episodes']} ({r['tried']} tried) | {r['env_steps']} | "
            f"{r['wall_total']:.1f} | **{rate:.1f}** | {ms['time_physics']:.1f} | "
            f"{ms['time_render']:.1f} | {ms['time_write']:.1f} | {other:.1f} | "
            f"{ms['cpu_seconds']:.1f} | "
            f"{cpu_bound:.0f} | {per_100:.1f} | {ok} |")


def main() -> None:
    """Parse arguments, run each worker count in a child process, print the table."""
    if len(sys.argv) >= 3 and sys.argv[1] == "--child":
        child_main(sys.argv[2])
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--episodes", type=int, default=10, help="episodes per config (default 10)")
    p.add_argument("--workers", default="1,2", help="comma-separated worker counts (1,2)")
    p.add_argument("--image-size", default="480x640", help="HEIGHTxWIDTH per camera")
    p.add_argument("--vcodec", default="h264", choices=["h264", "libsvtav1"])
    p.add_argument("--dart-noise", type=float, default=0.0)
    p.add_argument("--quick", action="store_true", help="2 episodes at 96x128: sanity run")
    p.add_argument("--out-dir", type=Path, default=None,
                   help="where the temporary datasets go (default: the system temp folder)")
    p.add_argument("--json", type=Path, default=None, help="also write raw results here")
    args = p.parse_args()
    if args.quick:
        args.episodes, args.image_size = 2, "96x128"
    h, w = parse_image_size(args.image_size)
    worker_counts = [int(v) for v in args.workers.split(",") if v.strip()]
    cores = len(os.sched_getaffinity(0))

    load_start = os.getloadavg()
    print(f"bench_record: {args.episodes} episodes per config at {h}x{w}, vcodec "
          f"{args.vcodec}, workers {worker_counts}, {cores} CPUs; load average "
          f"{load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}", flush=True)
    if args.out_dir is not None:
        args.out_dir.mkdir(parents=True, exist_ok=True)
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_record_", dir=args.out_dir) as tmp:
        for workers in worker_counts:
            job = {"out": str(Path(tmp) / f"w{workers}"), "episodes": args.episodes,
                   "image_size": [h, w], "workers": workers, "vcodec": args.vcodec,
                   "dart_noise": args.dart_noise}
            r = run_config(job, timeout=60 + 120 * args.episodes)
            results.append(r)
            print(f"  workers={workers}: {r['env_steps']} env-steps in {r['wall_total']:.1f} s "
                  f"= {r['env_steps'] / r['wall_total']:.1f} env-steps/s; load average now "
                  f"{os.getloadavg()[0]:.2f}", flush=True)
    load_end = os.getloadavg()

    print()
    print("| workers | episodes | env-steps | wall s | env-steps/s | physics ms/step | "
          "render ms/step | encode+write ms/step | other ms/step | CPU ms/step | "
          "CPU-bound max steps/s | 100 demos (min) | meets target |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        print(row(r, cores))
    print()
    print(f"- targets: >= {TARGET_STEPS_S:.0f} env-steps/s and 100 demos <= "
          f"{TARGET_100_MIN:.0f} min (2 workers on 2 cores), two {h}x{w} cameras, "
          f"{args.vcodec} video.")
    print("- physics / render / encode+write / other: wall ms per env step summed over the "
          "workers' loops (x workers x wall = their sum); encode+write is the writer as the "
          "loop sees it (feeding the encoder threads, waiting for an episode's videos, "
          "lerobot save_episode). Under CPU contention each includes time spent waiting for "
          "a core. CPU ms/step: all processes and threads (renderer and encoder threads "
          "included); CPU-bound max = CPUs x 1000 / CPU ms per step, the rate an idle machine "
          "allows.")
    print("- wall and env-steps/s are end to end: dataset creation, env/worker start-up and "
          "finalize included (only the one-off lerobot import is not); 100 demos = wall per "
          "kept episode x 100.")
    print(f"- load average (1/5/15 min): {load_start[0]:.2f} {load_start[1]:.2f} "
          f"{load_start[2]:.2f} at start, {load_end[0]:.2f} {load_end[1]:.2f} "
          f"{load_end[2]:.2f} at end, on {cores} CPUs; above {cores} means other processes "
          "took CPU time from the benchmark.")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))
        print(f"- raw results written to {args.json}")


if __name__ == "__main__":
    main()
