"""What the harness needs from a policy, and the adapters for the expert and step-wise policies.

A policy is anything with an ``info`` (``PolicyInfo``), ``start_episode(slot, seed)`` and
``predict_chunks(requests)``. The harness runs several envs ("slots") at once and asks for
actions only when a slot has used up its previous chunk, batching every such slot into one
``predict_chunks`` call. Keep per-episode state per slot, and derive any randomness from the
episode seed: then an episode's outcome does not depend on how many envs run beside it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from so101_sim.env import CAMERAS

Obs = dict[str, Any]


@dataclass(frozen=True)
class PolicyInfo:
    """Static facts about a policy that decide how the envs are run.

    ``cameras``: cameras it looks at (empty: no rendering except for videos).
    ``image_size``: (height, width) its cameras must have; frames rendered at another size go
    through ``so101_sim.image_pipeline.resize_frames`` first. ``train_image_size``: the size
    its training frames were recorded at (the default render size: the faithful path).
    ``n_obs_steps``: observations per request (To). ``n_action_steps``: actions returned per
    request and executed before the next one (Ta). ``fingerprint``: identifies the weights and
    settings, so ``--resume`` can refuse a different policy. ``details``: shown in the report.
    ``camera_map``: policy camera name -> env camera, for inputs named unlike the env's
    cameras (``--camera-map``); ``cameras`` lists the env cameras, which are what is rendered.
    """

    name: str
    cameras: tuple[str, ...] = ()
    needs_env_state: bool = False
    image_size: tuple[int, int] | None = None
    train_image_size: tuple[int, int] | None = None
    n_obs_steps: int = 1
    n_action_steps: int = 1
    fingerprint: str = ""
    details: dict[str, Any] = field(default_factory=dict)
    camera_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        unknown = set(self.cameras) - set(CAMERAS)
        if unknown:
            raise ValueError(f"policy {self.name!r} wants cameras {sorted(unknown)}; the env has "
                             f"{list(CAMERAS)}")
        if self.cameras and self.image_size is None:
            raise ValueError(f"policy {self.name!r} uses cameras but has no image_size; set "
                             "PolicyInfo(image_size=(height, width))")
        if self.n_obs_steps < 1 or self.n_action_steps < 1:
            raise ValueError(f"policy {self.name!r}: n_obs_steps={self.n_obs_steps}, "
                             f"n_action_steps={self.n_action_steps}; both must be >= 1")


@dataclass
class ChunkRequest:
    """One env that needs actions: its slot, episode seed and last ``n_obs_steps`` observations
    (oldest first; at the start of an episode the first observation is repeated).

    Observations are env-style dicts: ``agent_pos`` float32[6] (LeRobot units), ``pixels``
    ``{camera: uint8[h, w, 3]}`` at ``PolicyInfo.image_size`` when the policy has cameras, and
    ``environment_state`` float32[10] when it asked for it.
    """

    slot: int
    seed: int
    history: list[Obs]


@runtime_checkable
class EvalPolicy(Protocol):
    """The protocol a user policy implements to be evaluated by ``so101_sim.harness``."""

    info: PolicyInfo

    def start_episode(self, slot: int, seed: int) -> None:
        """Forget slot `slot`'s previous episode; a new one with `seed` starts there."""

    def predict_chunks(self, requests: Sequence[ChunkRequest]) -> np.ndarray:
        """Actions for every request: float array (len(requests), n_action_steps, 6)."""


class StepPolicy:
    """Adapts objects with ``reset(seed)`` and ``select_action(obs) -> action[6]`` (like
    ``ScriptedExpert`` or a hand-written controller): one object per slot, one action per call.
    """

    def __init__(self, factory: Callable[[], Any], info: PolicyInfo) -> None:
        if info.n_obs_steps != 1 or info.n_action_steps != 1:
            raise ValueError("StepPolicy acts one step at a time; use n_obs_steps=1 and "
                             "n_action_steps=1 in its PolicyInfo")
        self.info = info
        self._factory = factory
        self._slots: dict[int, Any] = {}

    def start_episode(self, slot: int, seed: int) -> None:
        if slot not in self._slots:
            self._slots[slot] = self._factory()
        self._slots[slot].reset(seed)

    def predict_chunks(self, requests: Sequence[ChunkRequest]) -> np.ndarray:
        out = [np.asarray(self._slots[r.slot].select_action(r.history[-1]), dtype=np.float32)
               for r in requests]
        return np.stack(out)[:, None, :]


def expert_policy(task: str | Path = "pick_place") -> StepPolicy:
    """The scripted expert as an ``EvalPolicy`` (reads the true cube pose: no cameras)."""
    from so101_sim.expert import ScriptedExpert
    from so101_sim.task import load_task

    spec = load_task(task)
    return StepPolicy(lambda: ScriptedExpert(spec),
                      PolicyInfo(name="expert", needs_env_state=True,
                                 fingerprint=f"so101_sim.expert.ScriptedExpert/{spec.name}"))


def load_policy(spec: str | Path, task: str | Path = "pick_place",
                **lerobot_options: Any) -> EvalPolicy:
    """``"expert"``, a lerobot checkpoint directory, or ``"package.module:factory"`` (a callable
    taking ``task`` and returning an ``EvalPolicy``)."""
    text = str(spec)
    if text == "expert":
        if lerobot_options:
            raise ValueError(f"options {sorted(lerobot_options)} apply to lerobot checkpoints, "
                             "not to --policy expert")
        return expert_policy(task)
    path = Path(text).expanduser()
    if not path.exists() and ":" in text and "/" not in text.split(":", 1)[0]:
        return _load_factory(text, task)
    from so101_sim.harness.lerobot_policy import LeRobotPolicy

    return LeRobotPolicy(path, **lerobot_options)


def _load_factory(text: str, task: str | Path) -> EvalPolicy:
    module_name, _, attr = text.partition(":")
    try:
        factory = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"--policy {text!r}: cannot import {attr!r} from {module_name!r} "
                         f"({exc}); expected 'expert', a checkpoint directory or "
                         "'package.module:factory'") from exc
    policy = factory(task=task)
    if not isinstance(policy, EvalPolicy):
        raise ValueError(f"--policy {text!r} returned {type(policy).__name__}, which lacks "
                         "`info`, `start_episode` or `predict_chunks` (see "
                         "so101_sim.harness.EvalPolicy)")
    return policy
