"""What the dataset on a lerobot-train command line holds, so the sim env that evaluates the
policy trained on it (``--env.type=so101_pick_place --env_eval_freq=N``) sends what it learnt
from: the same task, cameras and frame size.

lerobot-train builds the policy's inputs from the dataset and its evaluation envs from the env
config alone, checks nothing between them and resizes nothing. A policy fitted to 96x128 demos
given the env's default 480x640 frames stopped at its first evaluation step, after the training
before it, with "mat1 and mat2 shapes cannot be multiplied" (diffusion); a camera the env does
not send is a KeyError there; demos of ``stack`` evaluated on the default ``pick_place`` fail
every episode without a word. So, where the line names no local policy folder (that decides,
``policy_frames``) and no ``--config_path`` (a resumed run keeps its saved env config), the env
takes what the line leaves unset from the dataset's ``meta/info.json`` and so101-sim sidecar
(read as data), and warns about what the line sets otherwise, before training starts.
Imports neither torch nor lerobot.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from shlex import quote

import numpy as np

from so101_sim.dataset.reader import read_frames, recorded_task
from so101_sim.dataset.robot_episodes import read_robot_episodes
from so101_sim.policy_frames import (
    EVERY_CAMERA_TYPES,
    InputProblem,
    flag_value,
    policy_path,
    sets_frame_size,
)
from so101_sim.train.checkpoint import IMAGE_PREFIX, image_input_shapes


def _frame_size(feature: dict) -> tuple[int, int]:
    """(height, width) of a dataset's image feature, from its axis names where it has them."""
    shape, names = feature["shape"], feature.get("names") or []
    if "height" in names and "width" in names:
        return int(shape[names.index("height")]), int(shape[names.index("width")])
    return int(shape[0]), int(shape[1])  # lerobot writes (height, width, channels)


@dataclass(frozen=True)
class DatasetReads:
    """A local dataset named on a lerobot command line: its so101-sim task (from the recording
    sidecar of so101-sim record, else from the sim robot's note of the episodes lerobot-record
    saved when they share one task; None for any other dataset) and its cameras' frame sizes
    in ``meta/info.json`` order."""

    root: Path
    task: str | None
    sizes: dict[str, tuple[int, int]]

    @classmethod
    def of(cls, argv: Sequence[str], home: Path | None) -> DatasetReads | None:
        """The dataset of ``--dataset.root`` (else ``home/--dataset.repo_id``, lerobot's own
        default root), or None: no such folder, one we cannot read (lerobot-train will say),
        a local policy folder on the line, or a ``--config_path``."""
        if policy_path(argv) is not None or flag_value(argv, "--config_path") is not None:
            return None
        return cls.at(argv, home)

    @classmethod
    def at(cls, argv: Sequence[str], home: Path | None) -> DatasetReads | None:
        """The dataset the line names, whatever else it names (None: none we can read)."""
        root, repo = flag_value(argv, "--dataset.root"), flag_value(argv, "--dataset.repo_id")
        path = (Path(root).expanduser() if root else
                home / repo if repo and home is not None else None)
        if path is None or not (path / "meta" / "info.json").is_file():
            return None
        try:
            features = json.loads((path / "meta" / "info.json").read_text(encoding="utf-8"))
            sizes = {key[len(IMAGE_PREFIX):]: _frame_size(f)
                     for key, f in features["features"].items()
                     if key.startswith(IMAGE_PREFIX) and f.get("dtype") in ("video", "image")}
            task = recorded_task(path)
        except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError):
            return None
        return cls(path, task, sizes)

    def episode_seed(self, episode: int) -> int | None:
        """The reset seed of dataset episode `episode`: from the ``episode_seed`` column
        so101-sim record writes, else from the sim robot's note (None: neither has it)."""
        try:
            rows = read_frames(self.root, ["episode_index", "episode_seed"])
        except (OSError, ValueError, KeyError):
            return read_robot_episodes(self.root).get(episode, {}).get("seed")
        seeds = rows.loc[rows["episode_index"] == episode, "episode_seed"]
        return int(np.asarray(seeds.iloc[0]).reshape(-1)[0]) if len(seeds) else None

    def frame_size(self, argv: Sequence[str]) -> tuple[int, int] | None:
        """The one frame size of the dataset's cameras, where the line chooses none."""
        sizes = set(self.sizes.values())
        return sizes.pop() if len(sizes) == 1 and not sets_frame_size(argv) else None

    def mismatches(self, argv: Sequence[str], task: str, cameras: Sequence[str],
                   size: tuple[int, int]) -> list[InputProblem]:
        """What the env (`task`, `cameras`, `size`) sends unlike the dataset, each in one line
        with its fix: fatal for a missing camera when ``--policy.type`` reads every one (its
        first evaluation step would stop), else a warning."""
        kind = flag_value(argv, "--policy.type")
        head = f"dataset {self.root}"
        problems = []
        if missing := [cam for cam in self.sizes if cam not in cameras]:
            fix = ("drop --env.obs_type=state" if not cameras else
                   "drop --env.cameras (the env then sends the dataset's cameras)")
            fate = (f"a {kind} policy's first evaluation step would stop with KeyError "
                    f"'{IMAGE_PREFIX}{missing[0]}'" if kind in EVERY_CAMERA_TYPES else
                    "the policy trained on it would be evaluated without them")
            problems.append(InputProblem(
                f"{head} holds camera{'s' if len(missing) > 1 else ''} {', '.join(missing)}, "
                f"and this env sends {', '.join(cameras) or 'no camera frames'}: {fate}; {fix}",
                kind in EVERY_CAMERA_TYPES))
        if other := {cam: hw for cam, hw in self.sizes.items()
                     if cam in cameras and hw != tuple(size)}:
            h, w = next(iter(other.values()))
            shown = ", ".join(f"{cam} {hh}x{ww}" for cam, (hh, ww) in other.items())
            problems.append(InputProblem(
                f"{head} holds frames of {shown}, and this env sends {size[0]}x{size[1]}: "
                "lerobot resizes nothing on the way, so the policy trained on it would be "
                "evaluated on frames unlike its demos; drop --env.image_height and "
                f"--env.image_width, or set them to {h} and {w}", False))
        if self.task is not None and self.task != task:
            problems.append(InputProblem(
                f"{head} holds demos of task {self.task}, and --env.task={task} evaluates the "
                f"policy trained on them on {task}; drop --env.task, or pass "
                f"--env.task={self.task}" if flag_value(argv, "--env.task") is not None else
                f"{head} holds demos of task {self.task}, which does not load here, so the "
                f"policy trained on them would be evaluated on {task}; pass --env.task with "
                "that task's file", False))
        return problems


def fine_tune_problem(argv: Sequence[str], home: Path | None) -> str | None:
    """lerobot-train fine-tuning a local policy (``--policy.path``) on a dataset whose frames
    are not the policy's input size: it hands the policy the dataset's frames as they are, so
    the policy would learn from other pictures than it sees (the shipped 60x80 policy on the
    recorded 480x640 frames trains on 54x72 crops of them, without a word). None otherwise."""
    found = policy_path(argv)
    data = DatasetReads.at(argv, home) if found else None
    if found is None or data is None or flag_value(argv, "--config_path") is not None:
        return None
    try:
        takes = {cam: tuple(shape[1:3]) for cam, shape in image_input_shapes(found[0]).items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None  # lerobot-train will say what is wrong with it
    other = {cam: hw for cam, hw in data.sizes.items() if cam in takes and hw != takes[cam]}
    if not other:
        return None
    cam, (h, w) = next(iter(other.items()))
    th, tw = takes[cam]
    return (f"{found[0]} takes camera frames of {th}x{tw}, and dataset {data.root} holds "
            f"{h}x{w} ({cam}): lerobot-train hands a policy the dataset's frames as they are, "
            "so it would learn from other pictures than it sees; fine-tune it with `so101-sim "
            f"train --dataset {quote(str(data.root))} --init-from {quote(str(found[0]))} "
            f"--out RUN` (which resizes as its training did), or record the dataset at {th}x{tw}")


__all__ = ["DatasetReads", "fine_tune_problem"]
