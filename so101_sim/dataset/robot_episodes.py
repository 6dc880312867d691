"""The sim robot's note of each dataset episode it recorded: its seed and task.

A dataset that lerobot-record or lerobot-rollout writes with ``--robot.type=so101_sim`` holds
the frames, actions and task text, but not which seed and task file set up each episode's
scene, and replaying its actions on another seed misses the cube. So the robot appends one
JSON line per saved dataset episode to ``so101_sim_robot_episodes.jsonl`` in the dataset's
root (``so101-sim record`` keeps the same in its own ``episode_seed`` column and sidecar), and
lerobot-replay and lerobot-train read it back (``so101_sim.dataset_reads``). The file is data:
lines that do not parse, or whose fields have the wrong types, are skipped.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["ROBOT_EPISODES", "append_robot_episode", "noted_seeds", "noted_task",
           "read_robot_episodes"]

ROBOT_EPISODES = "so101_sim_robot_episodes.jsonl"


def append_robot_episode(root: Path, line: dict[str, Any]) -> None:
    """Append `line` (with ``dataset_episode``, ``seed`` and ``task``) to the dataset's file."""
    with open(Path(root) / ROBOT_EPISODES, "a", encoding="utf-8") as f:
        f.write(json.dumps(line) + "\n")


def read_robot_episodes(root: Path) -> dict[int, dict[str, Any]]:
    """{dataset episode: its line} ({} without the file). A later line for the same episode
    wins: a dataset recorded again from the same index (after its files were removed)."""
    try:
        text = (Path(root) / ROBOT_EPISODES).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return {}
    found: dict[int, dict[str, Any]] = {}
    for raw in text.splitlines():
        try:
            line = json.loads(raw)
        except ValueError:
            continue  # a line cut short by a kill
        if not isinstance(line, dict):
            continue
        episode, seed, task = line.get("dataset_episode"), line.get("seed"), line.get("task")
        if (type(episode) is int and episode >= 0 and type(seed) is int and seed >= 0
                and isinstance(task, str)):
            found[episode] = line
    return found


def noted_task(root: Path) -> str | None:
    """The one task of the noted episodes (None: no notes, or episodes of several tasks)."""
    tasks = {line["task"] for line in read_robot_episodes(root).values()}
    return tasks.pop() if len(tasks) == 1 else None


def noted_seeds(root: Path) -> list[int] | None:
    """The noted episodes' seeds in dataset-episode order (None: no notes)."""
    notes = read_robot_episodes(root)
    return [notes[e]["seed"] for e in sorted(notes)] if notes else None
