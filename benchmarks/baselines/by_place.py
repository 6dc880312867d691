"""Success by where the cube starts: per-seed evaluations binned by the cube's bearing.

    .venv/bin/python benchmarks/baselines/by_place.py \
        benchmarks/baselines/lift/suite_step_00{60,70}000.json

Each argument is an ``eval_info.json`` (or a folder holding one) with per-episode seeds; all
must be one task on the same seeds. Each seed is reset once (state only, no rendering) to read
the cube's start, and the seeds are cut into ``--bins`` equal-count bins of bearing around the
shoulder_pan axis (0 deg = straight ahead, negative = the robot's right, the side camera's
side). The table gives success per bin for each file (Wilson 95% interval for the last) and the
last file's failure modes. ``--demos DATASET`` adds how many of a recorded dataset's episodes
start in each bin, to tell thin coverage from a hard place.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from so101_sim.harness.stats import wilson_interval
from so101_sim.sim import PickPlaceEnv
from so101_sim.tasks.layouts import PAN_AXIS_XY


def _load(path: Path) -> tuple[str, dict[int, tuple[bool, str | None]]]:
    path = path / "eval_info.json" if path.is_dir() else path
    info = json.loads(path.read_text())
    try:
        task = info["config"]["task"]
        episodes = {int(e["seed"]): (bool(e["success"]), e.get("failure_mode"))
                    for e in info["per_episode"]}
    except (KeyError, TypeError) as exc:
        sys.exit(f"{path}: not an eval_info.json with per-episode seeds (missing {exc}); "
                 "pass the eval_info.json that `so101-sim eval` or `curve` wrote")
    return task, episodes


def bearings(task: str, seeds: list[int]) -> np.ndarray:
    """The cube's start bearing (degrees) around the pan axis, one reset per seed."""
    env = PickPlaceEnv(task=task, obs_type="state")
    try:
        out = []
        for seed in seeds:
            env.reset(seed=int(seed))
            x, y = env.cube_pos()[:2]
            out.append(math.degrees(math.atan2(y - PAN_AXIS_XY[1], x - PAN_AXIS_XY[0])))
        return np.array(out)
    finally:
        env.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("evals", nargs="+", type=Path, help="eval_info.json files (or folders)")
    ap.add_argument("--bins", type=int, default=4, help="equal-count bearing bins (default 4)")
    ap.add_argument("--demos", type=Path, help="a recorded dataset of the same task: its "
                    "episodes' start bearings per bin")
    args = ap.parse_args(argv)

    loaded = [_load(p) for p in args.evals]
    tasks = {t for t, _ in loaded}
    seeds = sorted(loaded[0][1])
    if len(tasks) != 1 or any(sorted(e) != seeds for _, e in loaded):
        sys.exit(f"the files are of tasks {sorted(tasks)} on different seeds; expected one task "
                 "on the same seeds (evaluations of one run's checkpoints, or paired runs)")
    task = tasks.pop()
    ang = bearings(task, seeds)
    edges = np.quantile(ang, np.linspace(0, 1, args.bins + 1))

    def bin_of(values: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, args.bins - 1)

    which = bin_of(ang)
    demo_bins = None
    if args.demos is not None:
        from so101_sim.dataset import stored_seeds

        d_ang = bearings(task, sorted(stored_seeds(args.demos)))
        demo_bins = np.bincount(bin_of(d_ang), minlength=args.bins)

    names = [p.stem if p.is_file() else p.name for p in args.evals]
    head = ["bearing (deg)", "n", *names, "95% CI (last)", "failures (last)"]
    if demo_bins is not None:
        head.insert(2, "demos")
    print(f"task {task}, {len(seeds)} seeds")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    last = loaded[-1][1]
    for b in range(args.bins):
        idx = [s for s, w in zip(seeds, which, strict=True) if w == b]
        rates = [sum(ep[s][0] for s in idx) for _, ep in loaded]
        lo, hi = wilson_interval(rates[-1], len(idx))
        modes = Counter(last[s][1] for s in idx if not last[s][0])
        row = [f"{edges[b]:.0f} to {edges[b + 1]:.0f}", str(len(idx)),
               *(f"{k}/{len(idx)} = {k / len(idx):.0%}" for k in rates),
               f"{lo:.0%}-{hi:.0%}", ", ".join(f"{m} {c}" for m, c in modes.most_common()) or "-"]
        if demo_bins is not None:
            row.insert(2, str(demo_bins[b]))
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
