"""The baselines' learning curves: one plot per run and task, and the rows of the status table.

    .venv/bin/python benchmarks/baselines/curves.py RUN [RUN ...] [--idle-steps-per-s R]

Each RUN is a `so101-sim train --out` folder whose checkpoints `so101-sim curve RUN --task T
--episodes N` has evaluated (RUN/eval_curve.jsonl). For every task found there it draws
success with its 95% Wilson interval against step and trainer hours into
`benchmarks/baselines/<run>_<task>.png` (`--plots DIR` elsewhere) and prints one markdown row per
evaluated checkpoint. Points may differ in seed count (64 along the way, 200 for a table
row); each carries its own interval, and `--episodes N` keeps only N-seed rows. Trainer
hours are the trainer's wall clock, pauses and CPU sharing included; with
`--idle-steps-per-s R` (the rate `bench_train_step.py` measures on an idle CPU) the plots'
hours axis and a column are idle-CPU hours instead: step / R.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from so101_sim.harness.curve import plot_curve, read_curve

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="`so101-sim train --out` folders")
    parser.add_argument("--episodes", type=int, default=None,
                        help="only curve rows of this many seeds (default: every row)")
    parser.add_argument("--plots", type=Path, default=HERE, help="where the PNGs go")
    parser.add_argument("--variant", default="",
                        help="the curve of `so101-sim curve --temporal-ensemble C` "
                             "(temporal_ensemble_coeff=C); default: the checkpoints' own setting")
    parser.add_argument("--idle-steps-per-s", type=float, default=None,
                        help="training steps per second on an idle CPU: hours = step / this")
    args = parser.parse_args(argv)
    rate = args.idle_steps_per_s
    hours = ("idle_hours", f"idle 2-core CPU hours (step / {rate} steps/s)") if rate else (
        "train_hours", "trainer wall hours (incl. pauses)")
    print(f"| run | task | step | {'idle CPU h' if rate else 'trainer h'} | success | 95% CI "
          "| failures |")
    print("|---|---|---|---|---|---|---|")
    def wanted(row: dict) -> bool:
        return args.episodes is None or row.get("episodes") == args.episodes

    for run in args.runs:
        rows = [r for r in read_curve(run, variant=args.variant) if wanted(r)]
        if not rows:
            which = f"{args.episodes}-seed rows" if args.episodes else "rows"
            raise SystemExit(f"{run}: no {which} in its eval_curve.jsonl; run `so101-sim curve "
                             f"{run} --task T --episodes {args.episodes or 64}` first")
        for task in sorted({r.get("task", "pick_place") for r in rows}):
            best: dict[int, dict] = {}  # a step measured twice (64 then 200): the larger
            for r in read_curve(run, task, args.variant):
                if wanted(r) and r["episodes"] >= best.get(r["step"], {"episodes": 0})["episodes"]:
                    best[r["step"]] = r
            curve = [best[s] for s in sorted(best)]
            counts = " or ".join(str(n) for n in sorted({r["episodes"] for r in curve}))
            for r in curve:
                r["idle_hours"] = r["step"] / rate / 3600 if rate else None
            name = f"{run.name}_{task}" + (f"_{args.variant}" if args.variant else "")
            png = plot_curve(curve, args.plots / f"{name}.png",
                             hours_key=hours[0], hours_label=hours[1],
                             title=f"run {run.name}, task {task}"
                                   + (f" ({args.variant})" if args.variant else "")
                                   + f": {counts} seeds from {curve[-1]['seed_start']} "
                                   "per checkpoint")
            for r in curve:
                lo, hi = (100 * x for x in r["ci95"])
                modes = ", ".join(f"{k} {v}" for k, v in sorted(
                    r["failure_modes"].items(), key=lambda kv: -kv[1])) or "none"
                print(f"| `{run.name}` | {task} | {r['step']} | {r[hours[0]]:.2f} | "
                      f"{r['successes']}/{r['episodes']} | {lo:.1f}-{hi:.1f} | {modes} |")
            print(f"<!-- plot: {png} -->")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
