"""The shipping decision of a ``ship_check.sh`` folder, as one table and one verdict line.

    .venv/bin/python benchmarks/baselines/ship_table.py OUT_DIR [--alpha 0.05]

Reads ``OUT_DIR/compare/<task>/compare.json`` (the candidate's fp16 copy against the shipped
card, seed by seed) and ``OUT_DIR/eval/<task>/eval_info.json`` (its failure modes) for every
task ship_check evaluated. The rule is the one every shipped checkpoint went through: ship
only a candidate that is measurably better (exact McNemar p < alpha, higher rate) on at least
one task and measurably worse on none.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

SHIPPED = Path(__file__).resolve().parents[2] / "policy" / "suite_diffusion"


def shipped_tasks(shipped: Path) -> list[str]:
    """The tasks the shipped card was measured on (its ``eval_info_<task>.json`` files), so a
    task added to the card is one more a candidate must be checked on."""
    return sorted(p.stem.removeprefix("eval_info_") for p in shipped.glob("eval_info_*.json"))


def _row(out: Path, task: str, alpha: float) -> tuple[str, str]:
    cmp_path = out / "compare" / task / "compare.json"
    info_path = out / "eval" / task / "eval_info.json"
    cmp = json.loads(cmp_path.read_text())
    agg = json.loads(info_path.read_text())["aggregated"]
    a, b, p = cmp["a"], cmp["b"], cmp["mcnemar_p_two_sided"]
    lo, hi = cmp["difference_ci95_pp"]
    diff = cmp["difference_pp"]
    verdict = "same" if p >= alpha else ("better" if diff > 0 else "worse")
    fails = ", ".join(f"{k} {v}" for k, v in sorted(agg["failure_modes"].items(),
                                                     key=lambda kv: -kv[1])) or "-"
    row = (f"| {task} | {a['n_success']}/{a['n_episodes']} = {a['pc_success']:.1f}% "
           f"({a['success_ci95'][0]:.1f}-{a['success_ci95'][1]:.1f}) | "
           f"{b['n_success']}/{b['n_episodes']} | {diff:+.1f} ({lo:+.1f} to {hi:+.1f}) | "
           f"{cmp['paired']['only_a']} / {cmp['paired']['only_b']} | {p:.3g} | {verdict} | "
           f"{fails} |")
    return row, verdict


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="the OUT_DIR given to ship_check.sh")
    ap.add_argument("--alpha", type=float, default=0.05,
                    help="two-sided McNemar level for 'measurably' (default 0.05)")
    ap.add_argument("--shipped", type=Path, default=SHIPPED,
                    help="the shipped checkpoint whose card sets the tasks (default %(default)s)")
    args = ap.parse_args(argv)
    tasks = shipped_tasks(args.shipped)
    if not tasks:
        sys.exit(f"{args.shipped}: no eval_info_<task>.json; expected a shipped checkpoint "
                 "with its card's evaluations (policy/suite_diffusion)")
    done = [t for t in tasks if (args.out / "compare" / t / "compare.json").is_file()]
    if not done:
        sys.exit(f"{args.out}: no compare/<task>/compare.json; expected the OUT_DIR of a "
                 "ship_check.sh run (run it first: bash benchmarks/baselines/ship_check.sh "
                 "CHECKPOINT OUT_DIR)")
    print("| task | candidate (fp16) | shipped | difference, 95% CI | discordant (cand. / "
          "shipped) | McNemar p | verdict | candidate's failures |")
    print("|---|---|---|---|---|---|---|---|")
    verdicts = {}
    for t in done:
        row, verdicts[t] = _row(args.out, t, args.alpha)
        print(row)
    better = [t for t, v in verdicts.items() if v == "better"]
    worse = [t for t, v in verdicts.items() if v == "worse"]
    missing = [t for t in tasks if t not in verdicts]
    if missing:
        print(f"undecided: not evaluated yet on {', '.join(missing)} (rerun ship_check.sh; "
              "finished tasks are skipped)")
    elif worse:
        print(f"do not ship: measurably worse on {', '.join(worse)}")
    elif better:
        print(f"ship: measurably better on {', '.join(better)}, worse on none "
              f"(copy {args.out / 'suite_diffusion'} to policy/suite_diffusion)")
    else:
        print("do not ship: nothing measurable on any task (a checkpoint is replaced only by a "
              "measurably better one)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
