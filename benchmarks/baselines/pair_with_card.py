"""Pair a look's per-seed results with the shipped suite_diffusion card, seed by seed.

    .venv/bin/python benchmarks/baselines/pair_with_card.py act_suite_te_step_0017500.json

For each task, `<task>/NAME` here against `policy/suite_diffusion/eval_info_<task>.json` on the
seeds both ran: success with its Wilson interval, the card's successes on those seeds, the
discordant seeds each way and the exact McNemar p. Prints one markdown table.
``--against OTHER`` pairs with an earlier look `<task>/OTHER` instead of the card, e.g. two
runs of the same recipe at the same step.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from so101_sim.harness.stats import mcnemar_p_value, wilson_interval

HERE = Path(__file__).resolve().parent
CARD = HERE.parents[1] / "policy" / "suite_diffusion"
TASKS = ("pick_place", "lift", "stack", "tidy", "pick_place_anywhere", "pick_place_dr")


def outcomes(path: Path) -> dict[int, dict]:
    return {e["seed"]: e for e in json.loads(path.read_text())["per_episode"]}


def row(task: str, name: str, against: str | None = None) -> str:
    look = outcomes(HERE / task / name)
    card = outcomes(HERE / task / against if against else CARD / f"eval_info_{task}.json")
    seeds = sorted(set(look) & set(card))
    if not seeds:
        raise SystemExit(f"{task}: no seed of {name} is in {against or 'the card'}'s run; "
                         "expected seeds from "
                         "100000 (evaluation seeds)")
    ok = sum(look[s]["success"] for s in seeds)
    ref = sum(card[s]["success"] for s in seeds)
    only_look = sum(look[s]["success"] and not card[s]["success"] for s in seeds)
    only_card = sum(card[s]["success"] and not look[s]["success"] for s in seeds)
    lo, hi = wilson_interval(ok, len(seeds))
    fails: dict[str, int] = {}
    for s in seeds:
        if not look[s]["success"]:
            mode = look[s]["failure_mode"] or "unknown"
            fails[mode] = fails.get(mode, 0) + 1
    modes = ", ".join(f"{m} {c}" for m, c in sorted(fails.items(), key=lambda x: -x[1])) or "none"
    p = mcnemar_p_value(only_look, only_card)
    return (f"| {task} | {ok}/{len(seeds)} = {100 * ok / len(seeds):.1f}% "
            f"({100 * lo:.1f}-{100 * hi:.1f}) | {modes} | {ref}/{len(seeds)} | "
            f"{only_look} / {only_card} | {p:.2g} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name", help="file under <task>/ here, e.g. act_suite_te_step_0017500.json")
    ap.add_argument("--against", metavar="OTHER", default=None,
                    help="pair with the look <task>/OTHER here instead of the suite_diffusion card")
    args = ap.parse_args()
    tasks = [t for t in TASKS if (HERE / t / args.name).exists()]
    if not tasks:
        raise SystemExit(f"{args.name}: no such file in any task's folder here ({HERE}/<task>/ "
                         f"for <task> in {', '.join(TASKS)}); expected a look's file name, "
                         "e.g. act_suite_te_step_0017500.json")
    for task in tasks:
        if args.against and not (HERE / task / args.against).exists():
            raise SystemExit(f"{task}: --against {args.against}: no file {task}/{args.against} "
                             f"here; expected a look's eval_info.json (ls {HERE / task})")
    ref = args.against or "card"
    print(f"| task | look (95% CI) | failures | {ref}, same seeds | only look / only {ref} | p |")
    print("|---|---|---|---|---|---|")
    for task in tasks:
        print(row(task, args.name, args.against))


if __name__ == "__main__":
    main()
