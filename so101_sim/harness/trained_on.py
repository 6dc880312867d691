"""What a checkpoint's demos were, from the ``so101_sim_train.json`` ``train`` writes (or, for a
lerobot-train checkpoint, the dataset or env its ``train_config.json`` names).

``eval`` and ``curve`` default ``--task`` to the demos' task (a policy trained on ``stack``
demos run on the default ``pick_place`` scores about 0 and looks broken), and say in one line
when the task asked for is not one the demos showed. The harness refuses to measure a policy on
evaluation seeds its demos hold (rollouts of ``eval --save-rollouts`` it was trained on): that
rate would be on its training data. Checkpoints that say none of this (older runs, other
trainers) keep the plain default, get no note and no check.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from so101_sim.tasks import TaskSpecError, load_task
from so101_sim.train.checkpoint import SEEDS_KEY, TASK_KEY, TEXTS_KEY, demos_of


def _info(checkpoint: str | Path) -> dict[str, Any]:
    return demos_of(Path(checkpoint).expanduser())


def trained_task(checkpoint: str | Path) -> str | None:
    """The task of the checkpoint's demos, if ``train`` recorded one that loads here."""
    task = _info(checkpoint).get(TASK_KEY)
    if not isinstance(task, str):
        return None
    try:
        load_task(task)
    except TaskSpecError as exc:  # a .toml path from another machine, or a renamed task
        print(f"note: {checkpoint} was trained on demos of {task!r}, which does not load here "
              f"({exc}); using the default task")
        return None
    return task


def default_task(policy: str, fallback: str) -> str:
    """``--task`` when none is given: the checkpoint's own task (said in one line), else
    `fallback`."""
    task = trained_task(policy)
    if task is None:
        return fallback
    if task != fallback:
        print(f"task: {task}, the task of the demos {policy} was trained on (--task to choose "
              "another)")
    return task


def unseen_task_note(checkpoint: str | Path, tasks: Sequence[str | Path],
                     flag: str = "--task", demos: dict[str, Any] | None = None) -> str | None:
    """One line naming the `tasks` whose text is not among those of the checkpoint's demos
    (None if every one is, or the checkpoint does not say); `flag` is the command's task
    option (lerobot-eval's is --env.task); `demos`: ``demos_of(checkpoint)`` if read already
    (for a lerobot-train checkpoint it reads the dataset)."""
    texts = (_info(checkpoint) if demos is None else demos).get(TEXTS_KEY)
    if not isinstance(texts, list) or not texts:
        return None
    unseen = [spec for spec in map(load_task, tasks) if spec.description not in texts]
    if not unseen:
        return None
    shown = "; ".join(repr(t) for t in texts[:3]) + ("; ..." if len(texts) > 3 else "")
    which = (f"{unseen[0].name} ({unseen[0].description!r})" if len(unseen) == 1
             else ", ".join(s.name for s in unseen))
    return (f"note: {which} {'is not a task' if len(unseen) == 1 else 'are not tasks'} "
            f"{checkpoint} was trained on (its demos: {shown}); expect a low rate"
            f"{'' if len(unseen) == 1 else ' there'}, or pass the {flag} it learned")


def check_unseen_seeds(demos: dict[str, Any], task: Any, seeds: Iterable[int],
                       allow_train_seeds: bool) -> None:
    """Refuse to measure a policy on evaluation seeds its demos hold for this task (rollouts
    of ``eval --save-rollouts`` it was trained on), unless `allow_train_seeds`."""
    ranges, own = demos.get(SEEDS_KEY) or [], demos.get(TASK_KEY)
    if allow_train_seeds or not ranges:
        return
    try:
        spans = [(int(lo), int(hi)) for lo, hi in ranges]
    except (TypeError, ValueError):
        raise ValueError(f"{SEEDS_KEY}={ranges!r} in the checkpoint's so101_sim_train.json is "
                         "invalid; expected [[first, last], ...]: re-export the checkpoint"
                         ) from None
    try:
        if own is not None and load_task(own).name != task.name:
            return  # another task's episodes on those seeds: other scenes
    except TaskSpecError:
        pass  # a task file that is not here: assume the same task
    seen = [s for s in seeds if any(lo <= s <= hi for lo, hi in spans)]
    if seen:
        from so101_sim.harness.compare import seed_ranges

        raise ValueError(
            f"{'seed' if len(seen) == 1 else 'seeds'} {seed_ranges(seen)} of {task.name} "
            f"{'is' if len(seen) == 1 else 'are'} among the policy's training "
            f"episodes ({SEEDS_KEY} in its so101_sim_train.json: rollouts it was trained on), "
            f"so the rate would measure its training data; evaluate on later seeds "
            f"(--seed-start {max(hi for _, hi in spans) + 1}); eval's --allow-train-seeds "
            "measures on them on purpose")
