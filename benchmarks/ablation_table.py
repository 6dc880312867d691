"""Print one markdown table for several evaluations of the same seeds, each paired with the first.

    .venv/bin/python benchmarks/ablation_table.py "DART + recoveries=RUN_A" "plain=RUN_B" ...

Each argument is LABEL=FOLDER, a finished `so101-sim eval --out` folder. All must share their
task and seeds (`so101-sim compare`'s rule); every row after the first is compared with the
first seed by seed: the difference with Newcombe's paired 95% interval and the exact McNemar p.
The training facts (dataset frames, step, trainer wall time) come from the checkpoint's
`so101_sim_train.json` when the eval's policy folder still has it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from so101_sim.harness.compare import check_comparable, load_run, paired_result


def _eval_info(run_dir: Path) -> dict:
    return json.loads((run_dir / "eval_info.json").read_text(encoding="utf-8"))


def _train_facts(info: dict) -> dict:
    """The evaluated checkpoint's so101_sim_train.json, or {} where it is gone."""
    checkpoint = info["config"].get("policy_details", {}).get("checkpoint")
    try:
        return json.loads((Path(checkpoint) / "so101_sim_train.json").read_text("utf-8"))
    except (TypeError, OSError, ValueError):
        return {}


def _failures(info: dict) -> str:
    modes = info["aggregated"].get("failure_modes", {})
    return ", ".join(f"{k} {v}" for k, v in sorted(modes.items())) or "none"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", metavar="LABEL=FOLDER")
    args = ap.parse_args(argv)
    pairs = []
    for arg in args.runs:
        label, sep, folder = arg.partition("=")
        if not sep or not label or not folder:
            print(f"ablation_table: {arg!r} is not LABEL=FOLDER; e.g. 'plain=runs/eval_plain'",
                  file=sys.stderr)
            return 2
        pairs.append((label, folder))
    try:  # a missing folder or runs on other seeds: compare's message, as one line
        pairs = [(label, load_run(folder)) for label, folder in pairs]
        for _, side in pairs[1:]:
            check_comparable(pairs[0][1], side)
    except (FileNotFoundError, ValueError) as exc:
        print(f"ablation_table: error: {exc}", file=sys.stderr)
        return 2
    ref_label, ref = pairs[0]
    print("| run | dataset frames | step | success | 95% CI | failures | "
          f"vs {ref_label} (paired) |")
    print("|---|---|---|---|---|---|---|")
    for label, side in pairs:
        d = side.to_dict()
        info = _eval_info(side.path)
        facts = _train_facts(info)
        lo, hi = d["success_ci95"]
        if side is ref:
            paired = "reference"
        else:
            r = paired_result(side, ref)
            plo, phi = r["difference_ci95_pp"]
            paired = (f"{r['difference_pp']:+.1f} pts ({plo:+.1f} to {phi:+.1f}), "
                      f"McNemar p = {r['mcnemar_p_two_sided']:.2g}")
        print(f"| {label} | {facts.get('dataset_frames', '?')} | {facts.get('step', '?')} | "
              f"{d['n_success']}/{d['n_episodes']} = {d['pc_success']:.1f}% | "
              f"{lo:.1f}-{hi:.1f} | {_failures(info)} | {paired} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
