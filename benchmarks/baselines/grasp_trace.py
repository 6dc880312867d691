"""What the gripper did in each episode of a ``--save-rollouts`` folder: its first close, and after.

    so101-sim eval --policy policy/suite_diffusion --task pick_place_anywhere --episodes 1 \\
        --seed-start 100056 --n-envs 1 --save-rollouts /tmp/ro100056
    .venv/bin/python benchmarks/baselines/grasp_trace.py /tmp/ro100056 [more folders ...]
    .venv/bin/python benchmarks/baselines/grasp_trace.py --count-reopens data/DEMOS

Each episode's executed actions are replayed from its seed in a state-only env (no rendering),
which reproduces the episode (a seed and an action sequence fix it), checked against the
recorded failure mode. One row per episode: the step the gripper command first closed
(below ``--closed`` after having opened above ``--open``), the nearest the finger pads came
to the first cube before that and when it closed, how far the cube had moved by the end, and
the widest the command opened again afterwards (a retry opens it past ``--open``). The
folders are data: only their parquet files and ``so101_sim_recording.json`` are read.

``--count-reopens`` reads the ``action`` column only (no replay) of any folder, rollouts or a
``so101-sim record`` dataset, and counts per episode how often the gripper opened again after
a close: 1 is a plain pick-and-place (the release), each retry of the recovering expert
(``record --recover``) adds one.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd

from so101_sim.dataset import SIDECAR, info_features, read_frames, read_sidecar
from so101_sim.sim import SO101Env

GRIPPER = 5  # action index of the gripper: 0 closed .. 100 open


def episodes(folder: Path) -> tuple[str, list[pd.DataFrame]]:
    """The task and one frame table per episode of a --save-rollouts or recorded folder.

    Each table has ``act``: the executed actions (``action_executed`` where a DART recording
    keeps them apart from the clean labels, else ``action``)."""
    features = info_features(folder)
    if not (folder / SIDECAR).is_file() or "action" not in features:
        sys.exit(f"{folder}: not a --save-rollouts or recorded folder (expected {SIDECAR} "
                 "and a LeRobotDataset with an `action` column); pass the DIR given to "
                 "`so101-sim eval --save-rollouts DIR` or `so101-sim record --out DIR`")
    executed = "action_executed" if "action_executed" in features else "action"
    columns = ["episode_index", "frame_index", "episode_seed", "action", executed]
    if "episode_failure_mode" in features:
        columns.append("episode_failure_mode")
    frames = read_frames(folder, list(dict.fromkeys(columns)))
    frames["act"] = frames[executed]
    return (read_sidecar(folder)["task"],
            [g.sort_values("frame_index") for _, g in frames.groupby("episode_index")])


def reopens(grip: np.ndarray, open_at: float, closed_at: float) -> int:
    """How many times the gripper command opens past `open_at` after closing below `closed_at`
    (the arm starts closed: the first opening, for the approach, is not counted)."""
    count, opened, closed = 0, False, False
    for v in grip:
        if v < closed_at:
            closed = opened
        elif v > open_at:
            count += closed
            opened, closed = True, False
    return count


def trace(task: str, ep: pd.DataFrame, open_at: float, closed_at: float) -> dict:
    """Replay one episode and summarise its first close and what followed."""
    seed = int(ep["episode_seed"].iloc[0])
    actions = np.stack(ep["act"].to_numpy()).astype(np.float32)
    env = SO101Env(task, obs_type="state")
    env.reset(seed=seed)
    start = env.cube_pos().copy()
    clearance, info = [], {}
    for a in actions:
        *_, info = env.step(a)
        clearance.append(env.pad_clearance())
    env.close()
    grip = actions[:, GRIPPER]
    opened = np.flatnonzero(grip > open_at)
    close = None
    if opened.size:
        after = np.flatnonzero(grip[opened[0]:] < closed_at)
        close = int(opened[0] + after[0]) if after.size else None
    recorded = ep["episode_failure_mode"].iloc[-1] if "episode_failure_mode" in ep else None
    row = {"seed": seed, "failure": info.get("failure_mode"),
           "replay_matches": (info.get("failure_mode") or None) == (recorded or None),
           "first_close": close}
    if close is not None:
        row["nearest_before_cm"] = round(100 * min(clearance[:close + 1]), 1)
        row["at_close_cm"] = round(100 * clearance[close], 1)
        row["cube_moved_cm"] = round(100 * float(np.linalg.norm((env.cube_pos() - start)[:2])), 1)
        row["most_open_after"] = round(float(grip[close:].max()))
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--open", type=float, default=30.0, help="gripper command counted as open")
    ap.add_argument("--closed", type=float, default=10.0,
                    help="gripper command counted as closed")
    ap.add_argument("--count-reopens", action="store_true",
                    help="per folder, episodes by how often the gripper reopened after a close")
    args = ap.parse_args(argv)
    loaded = [episodes(folder) for folder in args.folders]  # every folder checked first
    if args.count_reopens:
        for folder, (_, eps) in zip(args.folders, loaded, strict=True):
            counts = Counter(reopens(np.stack(ep["action"].to_numpy())[:, GRIPPER], args.open,
                                     args.closed) for ep in eps)
            print(f"{folder}: {len(eps)} episodes; by reopens after a close: "
                  + ", ".join(f"{k}: {counts[k]}" for k in sorted(counts)))
        return
    cols = ("seed", "failure", "replay_matches", "first_close", "nearest_before_cm",
            "at_close_cm", "cube_moved_cm", "most_open_after")
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for task, eps in loaded:
        for ep in eps:
            row = trace(task, ep, args.open, args.closed)
            print("| " + " | ".join(str(row.get(c, "")) for c in cols) + " |")


if __name__ == "__main__":
    main()
