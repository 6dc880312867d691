"""Success by where the cube starts (and, with --factors, by each randomized factor).

    .venv/bin/python benchmarks/baselines/by_place.py \
        benchmarks/baselines/lift/suite_step_00{60,70}000.json
    .venv/bin/python benchmarks/baselines/by_place.py --factors \
        benchmarks/baselines/pick_place_dr/suite_step_0060000.json

Each argument is an ``eval_info.json`` (or a folder holding one) with per-episode seeds; all
must be one task on the same seeds. Each seed is reset once (state only, no rendering) to read
the cube's start, and the seeds are cut into ``--bins`` equal-count bins of bearing around the
shoulder_pan axis (0 deg = straight ahead, negative = the robot's right, the side camera's
side; ``--cube K`` bins by cube K's start, for tidy's and stack's later cubes). The table
gives success per bin for each file (Wilson 95% interval for the last) and the last file's
failure modes. ``--demos DATASET`` adds how many of a recorded dataset's episodes
start in each bin, to tell thin coverage from a hard place.

``--factors`` reads, after each reset, every factor a ``[randomize]`` task drew (light, colours,
table pattern, camera offsets, cube physics, servos, distractors; plus the bearing) from the
env's model, and gives per factor the success of its low, middle and high third of the seeds
for each file, and for the last file the AUC of the failures (the chance that a failed seed's
value is above a successful one's: 0.5 = no association) with a two-sided permutation p-value.
With about 20 factors, only p below 0.05 / (their number) stands after Bonferroni.
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
from so101_sim.sim.glcheck import mujoco
from so101_sim.tasks.layouts import PAN_AXIS_XY

LUMA = np.array([0.299, 0.587, 0.114])  # Rec. 601 weights: how bright a colour looks


def _load(path: Path) -> tuple[str, dict[int, tuple[bool, str | None]]]:
    path = path / "eval_info.json" if path.is_dir() else path
    if not path.is_file():
        sys.exit(f"{path}: no such file; pass an eval_info.json that `so101-sim eval` or "
                 "`curve` wrote, or its folder")
    info = json.loads(path.read_text())
    try:
        task = info["config"]["task"]
        episodes = {int(e["seed"]): (bool(e["success"]), e.get("failure_mode"))
                    for e in info["per_episode"]}
    except (KeyError, TypeError) as exc:
        sys.exit(f"{path}: not an eval_info.json with per-episode seeds (missing {exc}); "
                 "pass the eval_info.json that `so101-sim eval` or `curve` wrote")
    return task, episodes


def bearings(task: str, seeds: list[int], cube: int = 0) -> np.ndarray:
    """Cube `cube`'s start bearing (degrees) around the pan axis, one reset per seed."""
    return factors(task, seeds, cube)["bearing (deg)"]


def _angle_deg(q: np.ndarray, q0: np.ndarray) -> float:
    """Rotation angle between two unit quaternions (degrees)."""
    return math.degrees(2 * math.acos(min(1.0, abs(float(np.dot(q, q0))))))


def factors(task: str, seeds: list[int], which: int = 0) -> dict[str, np.ndarray]:
    """Each randomized factor's value per seed, read from the env's model after one reset
    (state only). A task without ``[randomize]`` gives the bearing (of cube `which`) alone."""
    env = PickPlaceEnv(task=task, obs_type="state")
    try:
        if not 0 <= which < env.task.n_cubes:
            sys.exit(f"--cube {which}: task {task!r} has {env.task.n_cubes} cube(s), numbered "
                     f"0 to {env.task.n_cubes - 1} (0 is the red one); pass one of those")
        m = env.model
        key, table, cube = m.light("key").id, m.geom("table").id, env.ids.cube_geom
        cams = [m.camera(c).id for c in ("front", "side")]
        # read before the first reset: the model is still the nominal scene
        cam0 = (m.cam_pos[cams].copy(), m.cam_quat[cams].copy(), m.cam_fovy[cams].copy())
        kp0, damp0 = float(m.actuator_gainprm[0, 0]), float(m.dof_damping[env.ids.arm_qvel[0]])
        tex = m.texture("table_tex").id if mujoco.mj_name2id(
            m, mujoco.mjtObj.mjOBJ_TEXTURE, "table_tex") >= 0 else -1
        yellow = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_MATERIAL, "yellow")
        extra = [g for g in range(m.ngeom)
                 if (mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or "")
                 .startswith("distractor_")]
        rows: list[dict[str, float]] = []
        for seed in seeds:
            env.reset(seed=int(seed))
            x, y = env.cube_pos(which)[:2]
            row = {"bearing (deg)": math.degrees(math.atan2(y - PAN_AXIS_XY[1],
                                                            x - PAN_AXIS_XY[0]))}
            if env.task.randomize is not None:
                up = -m.light_dir[key]
                row["light azimuth (deg)"] = math.degrees(math.atan2(up[1], up[0]))
                row["light elevation (deg)"] = math.degrees(math.asin(float(up[2])))
                row["light intensity"] = float(m.light_diffuse[key, 0])
                row["ambient"] = float(m.vis.headlight.ambient[0])
                row["table luminance"] = float(LUMA @ m.geom_rgba[table, :3])
                if tex >= 0:  # texels are 255 * (1 - contrast * pattern), pattern in 0..1
                    n = m.tex_width[tex] * m.tex_height[tex] * 3
                    row["table pattern contrast"] = 1 - float(
                        m.tex_data[m.tex_adr[tex]:m.tex_adr[tex] + n].min()) / 255
                row["cube red"] = float(m.geom_rgba[cube, 0])
                row["cube green+blue"] = float(m.geom_rgba[cube, 1:3].mean())
                if yellow >= 0:
                    row["robot luminance"] = float(LUMA @ m.mat_rgba[yellow, :3])
                for i, name in enumerate(("front", "side")):
                    row[f"{name} camera shift (mm)"] = 1000 * float(
                        np.linalg.norm(m.cam_pos[cams[i]] - cam0[0][i]))
                    row[f"{name} camera turn (deg)"] = _angle_deg(m.cam_quat[cams[i]], cam0[1][i])
                    row[f"{name} camera fovy change (deg)"] = float(m.cam_fovy[cams[i]]
                                                                    - cam0[2][i])
                row["cube size (mm)"] = 2000 * float(m.geom_size[cube, 0])
                row["cube mass (g)"] = 1000 * float(m.body_mass[m.geom_bodyid[cube]])
                row["cube friction"] = float(m.geom_friction[cube, 0])
                row["servo gain factor"] = float(m.actuator_gainprm[0, 0]) / kp0
                row["servo damping factor"] = float(m.dof_damping[env.ids.arm_qvel[0]]) / damp0
                row["distractors"] = float(sum(m.geom_rgba[g, 3] > 0 for g in extra))
            rows.append(row)
        return {k: np.array([r[k] for r in rows]) for k in rows[0]}
    finally:
        env.close()


def failure_auc(values: np.ndarray, failed: np.ndarray, rng: np.random.Generator,
                permutations: int = 10000) -> tuple[float, float]:
    """P(a failed seed's value > a successful seed's value), ties half, and its two-sided
    permutation p-value (labels shuffled `permutations` times)."""
    ranks = _midranks(values)
    n_fail, n_ok = int(failed.sum()), int((~failed).sum())
    if n_fail == 0 or n_ok == 0:
        return float("nan"), float("nan")

    def auc(mask: np.ndarray) -> np.ndarray:
        u = (ranks * mask).sum(axis=-1) - n_fail * (n_fail + 1) / 2
        return u / (n_fail * n_ok)

    observed = float(auc(failed))
    shuffled = np.array([rng.permutation(failed) for _ in range(permutations)])
    null = auc(shuffled)
    p = (1 + int((np.abs(null - 0.5) >= abs(observed - 0.5) - 1e-12).sum())) / (1 + permutations)
    return observed, p


def _midranks(values: np.ndarray) -> np.ndarray:
    order = np.argsort(values, kind="stable")
    ranks = np.empty(len(values))
    ranks[order] = np.arange(1, len(values) + 1)
    for v in np.unique(values):  # ties share their mean rank
        tie = values == v
        ranks[tie] = ranks[tie].mean()
    return ranks


def factor_table(loaded: list, names: list[str], seeds: list[int], task: str) -> None:
    """Print success per third of each factor for every file, and the last file's AUC."""
    values = {k: v for k, v in factors(task, seeds).items() if np.ptp(v) > 0}  # drawn ones
    failed = np.array([not loaded[-1][1][s][0] for s in seeds])
    rng = np.random.default_rng(0)
    head = ["factor", "range seen", *(f"{n}: low / mid / high third" for n in names),
            "AUC of failures (last)", "p (last)"]
    print(f"task {task}, {len(seeds)} seeds, {int(failed.sum())} failures in the last file; "
          f"Bonferroni threshold for {len(values)} factors: p < {0.05 / len(values):.4f}")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for name, v in values.items():
        thirds = np.array_split(np.argsort(v, kind="stable"), 3)
        cells = []
        for _, ep in loaded:
            wins = [sum(ep[seeds[i]][0] for i in t) for t in thirds]
            cells.append(" / ".join(f"{w}/{len(t)}" for w, t in zip(wins, thirds, strict=True)))
        auc, p = failure_auc(v, failed, rng)
        print(f"| {name} | {v.min():.3g} to {v.max():.3g} | " + " | ".join(cells)
              + f" | {auc:.2f} | {p:.3g} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("evals", nargs="+", type=Path, help="eval_info.json files (or folders)")
    ap.add_argument("--bins", type=int, default=4, help="equal-count bearing bins (default 4)")
    ap.add_argument("--factors", action="store_true", help="success by each randomized "
                    "factor of the scene instead of by bearing bins")
    ap.add_argument("--task", help="the task file the evaluations ran (a .toml path), for a "
                    "task outside envs/; its name must be the one the files give")
    ap.add_argument("--cube", type=int, default=0, help="bin by this cube's start (tidy and "
                    "stack have several; 0, the red one, by default)")
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
    if args.task is not None:
        from so101_sim.tasks import load_task

        if load_task(args.task).name != task:
            sys.exit(f"--task {args.task} is task {load_task(args.task).name!r}, but the files "
                     f"are of {task!r}; pass the task file those evaluations ran")
        task = args.task
    if args.factors:
        factor_table(loaded, [p.stem if p.is_file() else p.name for p in args.evals], seeds,
                     task)
        return 0
    ang = bearings(task, seeds, args.cube)
    edges = np.quantile(ang, np.linspace(0, 1, args.bins + 1))

    def bin_of(values: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, args.bins - 1)

    which = bin_of(ang)
    demo_bins = None
    if args.demos is not None:
        from so101_sim.dataset import stored_seeds

        d_ang = bearings(task, sorted(stored_seeds(args.demos)), args.cube)
        demo_bins = np.bincount(bin_of(d_ang), minlength=args.bins)

    names = [p.stem if p.is_file() else p.name for p in args.evals]
    head = ["bearing (deg)", "n", *names, "95% CI (last)", "failures (last)"]
    if demo_bins is not None:
        head.insert(2, "demos")
    print(f"task {task}, {len(seeds)} seeds, binned by cube {args.cube}'s start")
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
