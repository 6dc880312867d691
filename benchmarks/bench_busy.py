"""How eval, record and train cope with a busy machine: thread and OpenMP wait settings, idle
vs one core taken by another process, side by side in one run.

    .venv/bin/python benchmarks/bench_busy.py [--policy policy/pick_place_diffusion]
        [--episodes 16] [--jobs eval,record,train] [--settings default,passive,spin,threads1]

Each cell runs the real command in a fresh child process (`so101-sim eval` on the shipped
policy, `so101-sim record` of a few episodes, `so101-sim train` for a few steps on that
recording) and reports its wall time. "busy" starts one spinning process (a pure-Python
loop, as a CI neighbour or a second job would be) for the duration of the cell. Settings:

- default: so101-sim's own choice (eval: half the cores for the policy; train: all cores
  while the others' CPU use is nil, else the batch in one part per core, one thread each,
  re-read every 2 s) and libgomp's own waits;
- all-cores: `--threads <cores>`, torch's default and so101-sim's before it chose;
- passive: OMP_WAIT_POLICY=PASSIVE (threads sleep at once when idle);
- spin: GOMP_SPINCOUNT=10000 (a short spin, then sleep);
- threads1: one torch thread (`--threads 1`), no thread pool to keep in step.

Run it on an otherwise idle machine: every other job is a third load.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXE = Path(sys.executable).parent / "so101-sim"
SETTINGS = {
    "default": ({}, []),
    # torch's own default before so101-sim chose threads itself: one thread per core
    "all-cores": ({}, ["--threads", str(os.cpu_count() or 1)]),
    "passive": ({"OMP_WAIT_POLICY": "PASSIVE"}, []),
    "spin": ({"GOMP_SPINCOUNT": "10000"}, []),
    "threads1": ({}, ["--threads", "1"]),
    # eval only: 16 envs, so half of them step while the policy runs the other half's forward
    "threads1-k16": ({}, ["--threads", "1", "--n-envs", "16"]),
}


def _busy() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def _run(cmd: list[str], env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    return time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", default=str(ROOT / "policy" / "pick_place_diffusion"))
    p.add_argument("--episodes", type=int, default=16)
    p.add_argument("--jobs", default="eval,record,train")
    p.add_argument("--settings", default=",".join(SETTINGS))
    p.add_argument("--train-steps", type=int, default=40)
    p.add_argument("--idle-only", default="", help="settings timed idle only (a reference "
                   "whose busy time is known to be long), comma-separated")
    args = p.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_busy_"))
    base_env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    base_env.setdefault("MUJOCO_GL", "egl")
    data = work / "demos"
    # a small recording for the train job (made once, idle, not timed)
    if "train" in args.jobs:
        _run([str(EXE), "record", "--episodes", "4", "--out", str(data), "--workers", "2"],
             base_env)

    def command(job: str, extra: list[str], n: int) -> list[str]:
        out = str(work / f"{job}_{n}")
        if job == "eval":
            return [str(EXE), "eval", "--policy", args.policy, "--episodes",
                    str(args.episodes), "--n-envs", "8", "--videos", "0", "--out", out, *extra]
        if job == "record":
            return [str(EXE), "record", "--episodes", "4", "--workers", "2", "--out", out,
                    *[x for x in extra if x != "1" and x != "--threads"]]
        return [str(EXE), "train", "--preset", "cpu", "--dataset", str(data), "--out", out,
                "--steps", str(args.train_steps), *extra]

    print(f"load average at start {os.getloadavg()[0]:.2f}; {os.cpu_count()} CPUs")
    print("\n| job | setting | idle s | busy s | busy/idle | vs default idle |")
    print("|---|---|---|---|---|---|")
    n = 0
    for job in args.jobs.split(","):
        ref = None
        for name in args.settings.split(","):
            env_extra, flags = SETTINGS[name]
            if job == "record" and (name.startswith("threads1") or name == "all-cores"):
                continue  # record has no torch thread pool
            if job != "eval" and "--n-envs" in flags:
                continue  # only eval has env workers that overlap the policy
            env = {**base_env, **env_extra}
            n += 1
            idle = _run(command(job, flags, n), env)
            busy = float("nan")
            if name not in args.idle_only.split(","):
                hog = _busy()
                try:
                    n += 1
                    busy = _run(command(job, flags, n), env)
                finally:
                    hog.kill()
                    hog.wait()
            ref = ref or idle
            print(f"| {job} | {name} | {idle:.1f} | {busy:.1f} | {busy / idle:.2f}x | "
                  f"idle {idle / ref:.2f}x, busy {busy / ref:.2f}x |", flush=True)
    print(f"load average at end {os.getloadavg()[0]:.2f}")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
