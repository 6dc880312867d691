"""What the harness needs from a policy, and the adapters for the expert and step-wise policies.

A policy is anything with an ``info`` (``PolicyInfo``), ``start_episode(slot, seed)`` and
``predict_chunks(requests)``. The harness runs several envs ("slots") at once and asks for
actions only when a slot has used up its previous chunk, batching every such slot into one
``predict_chunks`` call. Keep per-episode state per slot, and derive any randomness from the
episode seed: then an episode's outcome does not depend on how many envs run beside it.
Inside ``predict_chunks``, ``spare_core()`` says whether a core would otherwise idle until
the call returns (no env stepping, no other forward in flight), for a policy that can use
one without changing its results (the lerobot adapter's image encoder does).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from so101_sim.tasks import ALL_CAMERAS as CAMERAS

Obs = dict[str, Any]
_LOCAL = threading.local()  # the forward on this thread: may it take a second core?


@dataclass(frozen=True)
class PolicyInfo:
    """Static facts about a policy that decide how the envs are run.

    ``cameras``: cameras it looks at (empty: no rendering except for videos).
    ``image_size``: (height, width) its cameras must have; frames rendered at another size go
    through ``so101_sim.utils.image_pipeline.resize_frames`` first. ``train_image_size``: the size
    its training frames were recorded at (the default render size: the faithful path).
    ``n_obs_steps``: observations per request (To). ``n_action_steps``: actions returned per
    request and executed before the next one (Ta). ``fingerprint``: identifies the weights and
    settings, so ``--resume`` can refuse a different policy. ``weights``: the weights alone
    (``checks.weights_digest``), so an export can tell which checkpoint a result measured.
    ``details``: shown in the report.
    ``camera_map``: policy camera name -> env camera, for inputs named unlike the env's
    cameras (``--camera-map``); ``cameras`` lists the env cameras, which are what is rendered.
    ``demos``: what its training demos were, as ``train`` records them (``demos_of``).
    """

    name: str
    cameras: tuple[str, ...] = ()
    needs_env_state: bool = False
    image_size: tuple[int, int] | None = None
    train_image_size: tuple[int, int] | None = None
    n_obs_steps: int = 1
    n_action_steps: int = 1
    fingerprint: str = ""
    weights: str = ""
    details: dict[str, Any] = field(default_factory=dict)
    camera_map: dict[str, str] = field(default_factory=dict)
    demos: dict[str, Any] = field(default_factory=dict)

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


@contextmanager
def core_to_spare(spare: bool) -> Iterator[None]:
    """The harness runs ``predict_chunks`` in this block: `spare` says no env is stepping and
    no other forward is in flight, so a core would idle until this forward ends."""
    before = spare_core()
    _LOCAL.spare = spare
    try:
        yield
    finally:
        _LOCAL.spare = before


def spare_core() -> bool:
    """Inside ``predict_chunks``: may this forward use a second core (``core_to_spare``)?"""
    return getattr(_LOCAL, "spare", False)


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
