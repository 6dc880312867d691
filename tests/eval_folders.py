"""A finished `so101-sim eval --out` folder, written for a test: the parts of eval_info.json
that compare, ablation_table and ship_table read."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path


def write_eval_run(folder: Path, outcomes: dict[int, bool], *, name: str | None = None,
                   task: str = "pick_place", sha: str = "t" * 64,
                   images: str = "direct: rendered at 60x80",
                   failure: str = "never_grasped") -> Path:
    """`outcomes`: seed -> success; every failure is `failure`. `name` (default the folder's)
    is the policy's name and fingerprint, and tags each episode's action digest."""
    name = name or folder.name
    episodes = [{"seed": s, "success": ok, "actions_sha": f"{name}{s}",
                 "failure_mode": None if ok else failure} for s, ok in outcomes.items()]
    modes = Counter(e["failure_mode"] for e in episodes if e["failure_mode"])
    info = {"per_episode": episodes, "aggregated": {"failure_modes": dict(modes)},
            "config": {"policy": name, "policy_fingerprint": name, "task": task,
                       "task_sha256": sha, "images": images}}
    folder.mkdir(parents=True)
    (folder / "eval_info.json").write_text(json.dumps(info))
    return folder
