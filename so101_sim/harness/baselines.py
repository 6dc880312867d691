"""``--policy baseline``: the shipped Diffusion Policy baseline of a task (policy/baselines.toml).

The table is data: which checkpoint folder under ``policy/`` answers for a task, the card with
its measured success, and the recipe that trains it. A task with no shipped weights gets one
line naming its card and recipe instead.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from so101_sim.tasks import TaskSpec
from so101_sim.utils.paths import policy_dir

BASELINES_FILE = "baselines.toml"


def baselines() -> dict[str, dict[str, Any]]:
    """task name -> {checkpoint?, card, recipe}."""
    path = policy_dir() / BASELINES_FILE
    try:
        table = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path} is unreadable ({exc}); reinstall so101-sim") from None
    return {k: v for k, v in table.items() if isinstance(v, dict)}


def baseline_checkpoint(task: TaskSpec) -> Path:
    """The shipped checkpoint folder for `task`, or a ValueError naming the card and recipe."""
    table = baselines()
    entry = table.get(task.name)
    if entry is None:
        raise ValueError(f"--policy baseline: task {task.name!r} has no baseline entry; tasks "
                         f"with one: {sorted(table)}")
    if "checkpoint" not in entry:
        raise ValueError(f"--policy baseline: no weights are shipped for {task.name!r}; its "
                         f"card: {entry.get('card', '(none yet)')}; train it yourself: "
                         f"{entry.get('recipe', 'README.md, Baselines')}")
    folder = policy_dir() / entry["checkpoint"]
    if not (folder / "model.safetensors").is_file():
        raise ValueError(f"--policy baseline: {folder} has no model.safetensors; reinstall "
                         "so101-sim (the shipped weights are part of the package)")
    return folder
