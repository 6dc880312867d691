"""Which part of pick_place_dr's randomization costs the shipped suite policy its points.

Each ``tasks/pick_place_dr_<group>.toml`` is pick_place_dr with one group of its ``[randomize]``
section on and the rest at pick_place's nominal values; the cube's place is drawn from the
same stream as pick_place's, so seed s has the same layout in every variant. The evaluations
(training paused; about 4 min each on the 2 cores):

    for g in lights colours table_colour cube_colour robot_colour cameras physics distractors; do
      so101-sim eval --policy policy/suite_diffusion --episodes 200 \\
        --task benchmarks/baselines/tasks/pick_place_dr_$g.toml --out runs/dr_ablation/$g
    done

each ``eval_info.json`` kept as ``pick_place_dr/dr_<group>.json`` (video paths dropped). This
prints one row per group, paired seed by seed with the shipped card's own pick_place (nothing
randomized) and pick_place_dr (everything) evaluations, McNemar p on the discordant seeds:

    .venv/bin/python benchmarks/baselines/dr_groups.py
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

from so101_sim.harness.stats import mcnemar_p_value, wilson_interval

HERE = Path(__file__).resolve().parent
GROUPS = ("lights", "colours", "table_colour", "cube_colour", "robot_colour", "cameras",
          "physics", "distractors")


def outcomes(path: Path) -> dict[int, tuple[bool, str | None]]:
    """seed -> (success, failure mode) of one eval_info.json."""
    try:
        info = json.loads(path.read_text())
        return {int(e["seed"]): (bool(e["success"]), e.get("failure_mode"))
                for e in info["per_episode"]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        sys.exit(f"{path}: not a readable eval_info.json with per-episode seeds ({exc})")


def row(name: str, run: dict, nominal: dict, full: dict) -> str:
    """One table row: `run`'s rate, failures, and its discordant seeds against both cards."""
    k, n = sum(s for s, _ in run.values()), len(run)
    lo, hi = wilson_interval(k, n)
    modes = Counter(m for s, m in run.values() if not s)
    lost = sum(nominal[s][0] and not run[s][0] for s in run)
    won = sum(run[s][0] and not nominal[s][0] for s in run)
    kept = sum(run[s][0] and not full[s][0] for s in run)
    missed = sum(full[s][0] and not run[s][0] for s in run)
    return (f"| {name} | {k}/{n} = {100 * k / n:.1f}% ({100 * lo:.1f}-{100 * hi:.1f}) | "
            + (", ".join(f"{m} {c}" for m, c in modes.most_common()) or "none")
            + f" | {lost} / {won} | {mcnemar_p_value(lost, won):.2g} | {kept} / {missed} | "
            f"{mcnemar_p_value(kept, missed):.2g} |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--card", type=Path, default=HERE.parents[1] / "policy" / "suite_diffusion",
                    help="the shipped policy folder whose eval_info_<task>.json are paired")
    args = ap.parse_args(argv)
    nominal = outcomes(args.card / "eval_info_pick_place.json")
    full = outcomes(args.card / "eval_info_pick_place_dr.json")
    print("| randomized | success (95% CI) | failures | only pick_place / only this | p "
          "| only this / only pick_place_dr | p |")
    print("|---|---|---|---|---|---|---|")
    print(row("nothing (the card's pick_place)", nominal, nominal, full))
    for g in GROUPS:
        path = HERE / "pick_place_dr" / f"dr_{g}.json"
        if not path.exists():
            print(f"| {g} | not run ({path.name} missing) | | | | | |")
            continue
        run = outcomes(path)
        if sorted(run) != sorted(nominal):
            sys.exit(f"{path}: seeds {min(run)}..{max(run)} ({len(run)}) are not the card's "
                     f"{min(nominal)}..{max(nominal)} ({len(nominal)}); evaluate the card's seeds")
        print(row(g, run, nominal, full))
    print(row("everything (the card's pick_place_dr)", full, nominal, full))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
