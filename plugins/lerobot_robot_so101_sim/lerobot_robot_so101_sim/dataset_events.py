"""How a sim robot learns where lerobot's dataset episodes begin and end.

lerobot-record and lerobot-rollout time their episodes by the wall clock and never tell the
robot; the only calls that mark an episode are the dataset's. While a sim robot is connected,
``LeRobotDataset.add_frame``, ``save_episode`` and ``clear_episode_buffer`` are wrapped so that,
after lerobot's own method has run, every connected sim robot hears of it (``"frame"``,
``"saved"``, ``"discarded"``). The wrappers call the original first and change nothing else;
the last robot to disconnect puts the originals back. On a save the robot also notes the
episode's seed and task in the dataset (``note_saved_episode``).
"""

from __future__ import annotations

import functools
import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from so101_sim.dataset import ROBOT_EPISODES, append_robot_episode

EVENTS = {"add_frame": "frame", "save_episode": "saved", "clear_episode_buffer": "discarded"}
_ORIGINAL = "__so101_sim_original__"  # attribute of a wrapper: the method it wraps

_listeners: list[DatasetListener] = []
_lock = threading.Lock()


class DatasetListener(Protocol):
    def on_dataset_event(self, event: str, dataset: Any) -> None: ...


def watch_datasets(listener: DatasetListener) -> None:
    """Tell `listener` about every dataset frame, save and discard in this process."""
    with _lock:
        if listener not in _listeners:
            _listeners.append(listener)
        _install()


def unwatch_datasets(listener: DatasetListener) -> None:
    """Stop telling `listener`; with no listener left, restore lerobot's methods."""
    with _lock:
        if listener in _listeners:
            _listeners.remove(listener)
        if not _listeners:
            _uninstall()


def note_saved_episode(dataset: Any, line: dict[str, Any]) -> None:
    """Keep the seed and task of a saved dataset episode in the dataset's root
    (``so101_sim.dataset.robot_episodes``): lerobot's files do not, and lerobot-replay of the
    episode needs them. A dataset that cannot take the file is recorded as it is, with a
    warning."""
    root = getattr(dataset, "root", None)
    if root is None or line.get("dataset_episode") is None:
        return
    try:
        append_robot_episode(Path(root), line)
    except OSError as exc:
        logging.getLogger(__name__).warning(
            "so101_sim: could not write %s in %s (%s); lerobot-replay of dataset episode %d "
            "needs --robot.seed=%d --robot.task=%s", ROBOT_EPISODES, root, exc,
            line["dataset_episode"], line["seed"], line["task"])


def _dataset_class() -> type:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset


def _wrap(original: Callable[..., Any], event: str) -> Callable[..., Any]:
    @functools.wraps(original)
    def method(self: Any, *args: Any, **kwargs: Any) -> Any:
        result = original(self, *args, **kwargs)  # lerobot's work first, unchanged
        for listener in tuple(_listeners):
            listener.on_dataset_event(event, self)
        return result

    setattr(method, _ORIGINAL, original)
    return method


def _install() -> None:
    cls = _dataset_class()
    for name, event in EVENTS.items():
        current = cls.__dict__[name]
        if not hasattr(current, _ORIGINAL):
            setattr(cls, name, _wrap(current, event))


def _uninstall() -> None:
    cls = _dataset_class()
    for name in EVENTS:
        current = cls.__dict__.get(name)
        # Wrapped again by someone else since: leave theirs (ours, deeper, does nothing now).
        if hasattr(current, _ORIGINAL):
            setattr(cls, name, getattr(current, _ORIGINAL))
