"""Which task a checkpoint's demos were of, from the ``so101_sim_train.json`` ``train`` writes.

``eval`` and ``curve`` default ``--task`` to it (a policy trained on ``stack`` demos run on
the default ``pick_place`` scores about 0 and looks broken), and say in one line when the task
asked for is not one the demos showed. Checkpoints without these keys (older runs, other
trainers) keep the plain default and get no note.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from so101_sim.tasks import TaskSpecError, load_task
from so101_sim.train.checkpoint import TASK_KEY, TEXTS_KEY, read_train_info


def _info(checkpoint: str | Path) -> dict[str, Any]:
    path = Path(checkpoint).expanduser()
    return (read_train_info(path) or {}) if path.is_dir() else {}


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


def unseen_task_note(checkpoint: str | Path, tasks: Sequence[str | Path]) -> str | None:
    """One line naming the `tasks` whose text is not among those of the checkpoint's demos
    (None if every one is, or the checkpoint does not say)."""
    texts = _info(checkpoint).get(TEXTS_KEY)
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
            f"{'' if len(unseen) == 1 else ' there'}, or pass the --task it learned")
