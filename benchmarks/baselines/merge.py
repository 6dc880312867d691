"""Merge recorded datasets into one multi-task LeRobotDataset with lerobot's aggregation.

    python benchmarks/baselines/merge.py data/suite_120 data/pick_place_dart_120 data/lift_dart_120

Each source keeps its episodes and task string; the merged dataset's statistics are recomputed
from the sources' by lerobot. The output folder must not exist yet (a half-written merge is
deleted, never reused).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="merged dataset folder (must not exist)")
    ap.add_argument("sources", type=Path, nargs="+", help="dataset folders to merge, in order")
    args = ap.parse_args(argv)
    if args.out.exists():
        print(f"error: {args.out} exists; pick a new folder or delete it first", file=sys.stderr)
        return 2
    missing = [str(s) for s in args.sources if not (s / "meta" / "info.json").is_file()]
    if missing:
        print(f"error: not LeRobotDatasets (no meta/info.json): {missing}", file=sys.stderr)
        return 2
    from lerobot.datasets.aggregate import aggregate_datasets

    try:
        aggregate_datasets(
            repo_ids=[f"local/{s.name}" for s in args.sources],
            aggr_repo_id=f"local/{args.out.name}",
            roots=list(args.sources),
            aggr_root=args.out,
        )
    except BaseException:
        shutil.rmtree(args.out, ignore_errors=True)
        raise
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    meta = LeRobotDatasetMetadata(f"local/{args.out.name}", root=args.out)
    print(f"{args.out}: {meta.total_episodes} episodes, {meta.total_frames} frames, "
          f"tasks {sorted(meta.tasks.index)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
