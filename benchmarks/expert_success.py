"""Scripted-expert success rate over consecutive seeds, with its 95% Wilson interval.

    .venv/bin/python benchmarks/expert_success.py --seeds 500 [--seed-start 0]
    .venv/bin/python benchmarks/expert_success.py --seeds 200 --dart-noise 3 --recover

`--dart-noise` and `--recover` run the expert as `so101-sim record` would with those flags
(the same `run_episode`); the retries it started are counted by reason.

State observations only (no rendering): success is the env's own info["is_success"].
"""

from __future__ import annotations

import argparse
import collections
import time

from tqdm import tqdm

from so101_sim.expert import ScriptedExpert
from so101_sim.harness.stats import wilson_interval
from so101_sim.record import expert_options, run_episode
from so101_sim.sim import PickPlaceEnv


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=500)
    parser.add_argument("--seed-start", type=int, default=0)
    parser.add_argument("--task", default="pick_place")
    parser.add_argument("--dart-noise", type=float, default=0.0)
    parser.add_argument("--recover", action="store_true", help="expert retries failed attempts")
    parser.add_argument("--grasp-clearance", type=float, default=None,
                        help="fixed-jaw gap at the grasp in metres (default: the expert's)")
    args = parser.parse_args()

    env = PickPlaceEnv(task=args.task, obs_type="state")
    expert = ScriptedExpert(env.task, model=env.model,
                            **expert_options(args.recover, args.grasp_clearance))
    modes: collections.Counter[str] = collections.Counter()
    retries: collections.Counter[str] = collections.Counter()
    recovered = 0
    failed: list[tuple[int, str]] = []
    t0 = time.perf_counter()
    for seed in tqdm(range(args.seed_start, args.seed_start + args.seeds), unit="episode"):
        success, mode, _ = run_episode(env, expert, seed, lambda frame: None, args.dart_noise)
        mode = "success" if success else mode
        retries.update(expert.retry_log)
        recovered += bool(success and expert.retries)
        modes[mode] += 1
        if mode != "success":
            failed.append((seed, mode))
    k, n = modes["success"], args.seeds
    lo, hi = wilson_interval(k, n)
    print(f"expert success {k}/{n} = {100 * k / n:.2f}% (95% Wilson [{100 * lo:.2f}, "
          f"{100 * hi:.2f}]) seeds {args.seed_start}..{args.seed_start + n - 1}, "
          f"{time.perf_counter() - t0:.1f} s")
    print("outcomes:", dict(modes))
    if args.recover:
        print(f"retries started: {dict(retries)}; successes after a retry: {recovered}")
    if failed:
        print("failed seeds:", failed)


if __name__ == "__main__":
    main()
