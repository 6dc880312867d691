"""The image encoder split over two cores (harness.policies.encoder_split): the same actions."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from so101_sim.harness.policies.encoder_split import (
    MIN_HALF,
    SplitEncoder,
    use_split_encoder,
    use_whole_encoder,
)
from so101_sim.harness.policies.lerobot import LeRobotPolicy

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_forward_rows import chunks as _chunks  # noqa: E402  (one way to build requests)
from bench_forward_rows import requests as _requests  # noqa: E402


def test_the_shipped_policy_gives_the_same_actions_with_its_encoder_split():
    """Full and padded forwards, split wherever the load-time check allowed it."""
    path = ROOT / "policy" / "pick_place_diffusion"
    quiet = lambda _: None  # noqa: E731
    fast = LeRobotPolicy(path, log=quiet)
    split = fast.policy.diffusion.rgb_encoder.forward
    assert isinstance(split, SplitEncoder)
    split.spare = lambda: True  # as if the other core were idle, whatever this machine has
    plain = LeRobotPolicy(path, log=quiet)
    assert use_whole_encoder(plain.policy) == 1 and use_whole_encoder(plain.policy) == 0
    assert list(fast.policy.state_dict()) == list(plain.policy.state_dict())
    reqs = _requests(fast, 11)  # one full forward of 8 rows (32 images) and one padded
    np.testing.assert_array_equal(_chunks(fast, reqs), _chunks(plain, reqs))
    # The load's own row check asked the question for the forward's shape, with its threads.
    ((shape, _, threads), exact), = split._exact.items()
    assert shape[0] == 8 * 2 * 2 and threads == torch.get_num_threads()
    assert split.splits == (2 if exact else 0)


class DiffusionRgbEncoder(nn.Module):
    """Stands in for lerobot's encoder (found by class name); `mixes` makes every image's
    features depend on its batch, as a kernel chosen by batch size could."""

    def __init__(self, mixes: bool = False) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.tensor(2.0))
        self.mixes = mixes

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = x.flatten(1)[:, :4] * self.scale
        return out + x.shape[0] if self.mixes else out


def _split(mixes: bool, spare: bool = True) -> tuple[nn.Module, SplitEncoder]:
    holder = nn.Sequential(DiffusionRgbEncoder(mixes)).eval()
    assert use_split_encoder(holder, lambda: spare) == 1
    return holder[0], holder[0].forward


def test_the_halves_are_used_only_where_they_keep_every_bit():
    x = torch.rand(2 * MIN_HALF, 3, 4, 5, generator=torch.Generator().manual_seed(0))
    enc, split = _split(mixes=False)
    with torch.no_grad():
        want = split.whole(x)
        for _ in range(3):  # the first call checks the halves, the next ones split
            assert torch.equal(enc(x), want)
    assert split.splits == 2 and list(split._exact.values()) == [True]
    enc, split = _split(mixes=True)
    with torch.no_grad():
        want = split.whole(x)
        for _ in range(3):
            assert torch.equal(enc(x), want)
    assert split.splits == 0 and list(split._exact.values()) == [False]


@pytest.mark.parametrize("case", ["small", "odd", "grad", "train", "autocast", "busy"])
def test_the_encoder_stays_whole_where_a_split_might_not_hold(case):
    n = {"small": 2 * MIN_HALF - 2, "odd": 2 * MIN_HALF + 1}.get(case, 2 * MIN_HALF)
    x = torch.rand(n, 3, 4, 5, generator=torch.Generator().manual_seed(1))
    enc, split = _split(mixes=False, spare=case != "busy")
    if case == "train":
        enc.train()
    grad = torch.enable_grad() if case == "grad" else torch.no_grad()
    cast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=case == "autocast")
    with grad, cast:
        for _ in range(3):
            enc(x)
    assert split.splits == 0
    assert bool(split._exact) == (case == "busy")  # asked only when a split could run
