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

``--every-close`` replays the same way and gives one row per close of the command, on every
cube (tidy has three): which cube the pads were nearest, how many steps later the tool had
risen 1 cm, each pad's distance to that cube and the gripper joint's angle at that moment (a
cube between the jaws stops them: both pads touching, the joint open by the cube's width), and
how far the tool and the cube rose before the next opening (a held cube rises with the tool).

``--expert-pan`` adds the shoulder_pan command (degrees) at that first close, and the scripted
expert's at its own close on the same seed (no noise): where they differ by more than a few
degrees the arm closed beside the cube, not on it (the right-hand corner of
pick_place_anywhere, the baselines page, "twenty-seventh session").

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

import mujoco
import numpy as np
import pandas as pd

from so101_sim.dataset import SIDECAR, info_features, read_frames, read_sidecar
from so101_sim.expert import ScriptedExpert
from so101_sim.sim import SO101Env
from so101_sim.utils.text import counted

GRIPPER = 5  # action index of the gripper: 0 closed .. 100 open
PAN = 0  # action index of shoulder_pan


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
        row["pan_at_close"] = round(float(actions[close, PAN]), 1)
    return row


def expert_pan_at_close(task: str, seed: int, limit: int = 300) -> float | None:
    """The scripted expert's shoulder_pan command when it starts closing on `seed`."""
    env = SO101Env(task, obs_type="state")
    expert = ScriptedExpert(env.task, model=env.model)
    obs, _ = env.reset(seed=seed)
    expert.reset(seed=seed)
    try:
        for _ in range(limit):
            action = expert.select_action(obs)
            if expert.phase == "close":
                return round(float(action[PAN]), 1)
            obs, *_ = env.step(action)
    finally:
        env.close()
    return None


def _pads_cm(env: SO101Env, k: int) -> tuple[float, float]:
    m, d, ids = env.model, env.data, env.ids
    return tuple(round(100 * mujoco.mj_geomDistance(m, d, ids.cube_geoms[k], pad, 0.05, None), 1)
                 for pad in (ids.fixed_pad, ids.moving_pad))


def every_close(task: str, ep: pd.DataFrame, open_at: float, closed_at: float) -> list[dict]:
    """Replay one episode; one row per close of the gripper command (see the module doc)."""
    seed = int(ep["episode_seed"].iloc[0])
    actions = np.stack(ep["act"].to_numpy()).astype(np.float32)
    env = SO101Env(task, obs_type="state")
    env.reset(seed=seed)
    n_cubes = getattr(env.task, "n_cubes", 1)
    rows: list[dict] = []
    row: dict | None = None
    opened = False
    for t, a in enumerate(actions):
        env.step(a)
        tool_z = float(env.data.site_xpos[env.ids.tcp_site][2])
        if a[GRIPPER] < closed_at and opened and row is None:
            clearance = [env.pad_clearance(k) for k in range(n_cubes)]
            k = int(np.argmin(clearance))
            row = {"seed": seed, "close": t, "cube": k,
                   "at_close_cm": round(100 * clearance[k], 1), "_t0": tool_z, "_top": tool_z,
                   "_c0": float(env.cube_pos(k)[2]), "_ctop": float(env.cube_pos(k)[2])}
        elif a[GRIPPER] > open_at:
            opened = True
            if row is not None:
                rows.append(row)
                row = None
        if row is not None:
            if "rise_1cm_after" not in row and tool_z - row["_t0"] > 0.01:
                row["rise_1cm_after"] = t - row["close"]
                row["pads_at_rise_cm"] = "/".join(map(str, _pads_cm(env, row["cube"])))
                row["gripper_deg_at_rise"] = round(float(np.degrees(env.data.qpos[GRIPPER])))
            row["_top"] = max(row["_top"], tool_z)
            row["_ctop"] = max(row["_ctop"], float(env.cube_pos(row["cube"])[2]))
    env.close()
    if row is not None:
        rows.append(row)
    for r in rows:
        r["tool_rose_cm"] = round(100 * (r.pop("_top") - r.pop("_t0")), 1)
        r["cube_rose_cm"] = round(100 * (r.pop("_ctop") - r.pop("_c0")), 1)
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--open", type=float, default=30.0, help="gripper command counted as open")
    ap.add_argument("--closed", type=float, default=10.0,
                    help="gripper command counted as closed")
    ap.add_argument("--count-reopens", action="store_true",
                    help="per folder, episodes by how often the gripper reopened after a close")
    ap.add_argument("--expert-pan", action="store_true",
                    help="add the pan at the first close and the expert's on the same seed")
    ap.add_argument("--every-close", action="store_true",
                    help="one row per close on any cube: did the cube rise with the tool")
    args = ap.parse_args(argv)
    loaded = [episodes(folder) for folder in args.folders]  # every folder checked first
    if args.every_close:
        cols = ("seed", "close", "cube", "at_close_cm", "rise_1cm_after", "pads_at_rise_cm",
                "gripper_deg_at_rise", "tool_rose_cm", "cube_rose_cm")
        print("| " + " | ".join(cols) + " |")
        print("|" + "---|" * len(cols))
        for task, eps in loaded:
            for ep in eps:
                for row in every_close(task, ep, args.open, args.closed):
                    print("| " + " | ".join(str(row.get(c, "")) for c in cols) + " |")
        return
    if args.count_reopens:
        for folder, (_, eps) in zip(args.folders, loaded, strict=True):
            counts = Counter(reopens(np.stack(ep["action"].to_numpy())[:, GRIPPER], args.open,
                                     args.closed) for ep in eps)
            print(f"{folder}: {counted(len(eps), 'episode')}; by reopens after a close: "
                  + ", ".join(f"{k}: {counts[k]}" for k in sorted(counts)))
        return
    cols = ("seed", "failure", "replay_matches", "first_close", "nearest_before_cm",
            "at_close_cm", "cube_moved_cm", "most_open_after")
    if args.expert_pan:
        cols += ("pan_at_close", "expert_pan_at_close")
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for task, eps in loaded:
        for ep in eps:
            row = trace(task, ep, args.open, args.closed)
            if args.expert_pan:
                row["expert_pan_at_close"] = expert_pan_at_close(task, row["seed"])
            print("| " + " | ".join(str(row.get(c, "")) for c in cols) + " |")


if __name__ == "__main__":
    main()
