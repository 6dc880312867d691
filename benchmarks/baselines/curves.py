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

    .venv/bin/python benchmarks/baselines/curves.py --name RUN --files FILE[:STEP] ... \
        --idle-steps-per-s R

draws the same plot from per-seed `eval_info.json` files (the ones committed under
`benchmarks/baselines/<task>/`), for runs whose folder is gone: each FILE is one checkpoint,
its step taken from `step_NNNNNNN` in the name unless given after a colon (e.g. a fine-tune's
starting weights as step 0).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from so101_sim.harness.curve import curve_row, plot_curve, read_curve
from so101_sim.harness.results import check_eval_info

HERE = Path(__file__).resolve().parent


def rows_from_files(specs: list[str]) -> list[dict]:
    """Curve rows from per-seed `eval_info.json` files, given as FILE or FILE:STEP."""
    rows = []
    for spec in specs:
        path, _, step = spec.partition(":")
        if not step:
            m = re.search(r"step_(\d+)", Path(path).name)
            if m is None:
                raise SystemExit(f"--files {spec}: no step_NNNNNNN in its name; give the step "
                                 f"as {path}:STEP")
            step = m.group(1)
        try:  # data, not code: the harness's own checks of an eval_info.json
            info = json.loads(Path(path).read_text())
            check_eval_info(info, Path(path))
            cfg, episodes = info["config"], info["per_episode"]
            modes = info["aggregated"]["failure_modes"]  # as the run printed them
        except (OSError, ValueError, KeyError) as e:
            raise SystemExit(f"--files {path}: not a readable eval_info.json ({e}); pass the "
                             "per-seed file `so101-sim eval` writes") from None
        rows.append(curve_row(cfg["task"], int(step), sum(e["success"] for e in episodes),
                              len(episodes), cfg["seed_start"], modes))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="*", type=Path, help="`so101-sim train --out` folders")
    parser.add_argument("--files", nargs="+", default=None, metavar="FILE[:STEP]",
                        help="per-seed eval_info.json files, one per checkpoint, instead of RUNs")
    parser.add_argument("--name", default=None, help="the run's name for --files")
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

    curves: list[tuple[str, str, list[dict]]] = []  # (run name, task, rows by step)
    if args.files:
        if args.runs or not args.name or not rate:
            parser.error("--files takes --name and --idle-steps-per-s, and no RUN folders")
        rows = sorted(rows_from_files(args.files), key=lambda r: r["step"])
        for task in sorted({r["task"] for r in rows}):
            curves.append((args.name, task, [r for r in rows if r["task"] == task]))
    elif not args.runs:
        parser.error("give RUN folders, or --files with --name")
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
            curves.append((run.name, task, [best[s] for s in sorted(best)]))

    for run_name, task, curve in curves:
        counts = " or ".join(str(n) for n in sorted({r["episodes"] for r in curve}))
        for r in curve:
            r["idle_hours"] = r["step"] / rate / 3600 if rate else None
        name = f"{run_name}_{task}" + (f"_{args.variant}" if args.variant else "")
        png = plot_curve(curve, args.plots / f"{name}.png",
                         hours_key=hours[0], hours_label=hours[1],
                         title=f"run {run_name}, task {task}"
                               + (f" ({args.variant})" if args.variant else "")
                               + f": {counts} seeds from {curve[-1]['seed_start']} "
                               "per checkpoint")
        for r in curve:
            lo, hi = (100 * x for x in r["ci95"])
            modes = ", ".join(f"{k} {v}" for k, v in sorted(
                r["failure_modes"].items(), key=lambda kv: -kv[1])) or "none"
            print(f"| `{run_name}` | {task} | {r['step']} | {r[hours[0]]:.2f} | "
                  f"{r['successes']}/{r['episodes']} | {lo:.1f}-{hi:.1f} | {modes} |")
        print(f"<!-- plot: {png} -->")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
