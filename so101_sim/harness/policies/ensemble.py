"""ACT's temporal ensembling, one ensembler per env slot.

With ``temporal_ensemble_coeff`` set, an ACT policy predicts a whole chunk every step and
executes the exponentially weighted average of every chunk's prediction for this step (ACT,
Algorithm 2). lerobot's ``ACTPolicy.select_action`` keeps that running average for one fixed
batch of envs; the harness batches whichever envs are waiting, so each slot gets its own
``ACTTemporalEnsembler`` (lerobot's), reset when the slot starts an episode.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch


class SlotEnsemblers:
    def __init__(self, coeff: float, chunk_size: int) -> None:
        self.coeff, self.chunk_size = float(coeff), int(chunk_size)
        self._slots: dict[int, object] = {}

    def start(self, slot: int) -> None:
        from lerobot.policies.act.modeling_act import ACTTemporalEnsembler

        self._slots[slot] = ACTTemporalEnsembler(self.coeff, self.chunk_size)

    def step(self, slots: Sequence[int], chunks: torch.Tensor) -> torch.Tensor:
        """(rows, chunk, dim) predictions -> (rows, 1, dim): this step's ensembled action."""
        rows = [self._slots[s].update(chunks[j:j + 1]) for j, s in enumerate(slots)]
        return torch.cat(rows)[:, None, :]
