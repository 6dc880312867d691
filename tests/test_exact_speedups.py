"""The harness's exact speed-ups: channels-last max pooling and a heap that keeps freed memory."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_policy import make_tiny_diffusion_checkpoint
from torch import nn

from so101_sim.harness.policies.lerobot import LeRobotPolicy
from so101_sim.harness.policies.pooling import (
    ChannelsLastMaxPool2d,
    use_channels_last_pooling,
    use_default_pooling,
)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_forward_rows import chunks as _chunks  # noqa: E402  (one way to build requests)
from bench_forward_rows import requests as _requests  # noqa: E402


@pytest.mark.parametrize("shape,kwargs", [
    ((32, 64, 27, 36), {"kernel_size": 3, "stride": 2, "padding": 1}),  # the ResNet-18 stem
    ((3, 5, 11, 7), {"kernel_size": 2, "stride": 2, "ceil_mode": True}),
    ((2, 4, 9, 9), {"kernel_size": 3, "stride": 1, "padding": 1, "dilation": 1}),
])
def test_pooled_values_are_the_default_kernels_and_the_output_stays_nchw(shape, kwargs):
    # After a ReLU most of a window can be tied at zero; a maximum is exact, so ties do not matter.
    x = torch.relu(torch.randn(shape, generator=torch.Generator().manual_seed(0)))
    x[0, 0, :3, :3] = float("nan")
    plain, fast = nn.MaxPool2d(**kwargs), ChannelsLastMaxPool2d(**kwargs)
    with torch.no_grad():
        want, got = plain(x), fast(x)
    assert got.is_contiguous() and got.shape == want.shape
    assert torch.equal(torch.nan_to_num(got, nan=-1.0), torch.nan_to_num(want, nan=-1.0))
    assert torch.equal(got.isnan(), want.isnan())


def test_with_gradients_on_the_default_kernel_runs_and_gradients_are_unchanged():
    # Tied maxima could route a gradient to another element in the channels-last kernel.
    x = torch.relu(torch.randn(4, 8, 12, 12, generator=torch.Generator().manual_seed(1)))
    grads = []
    for pool in (nn.MaxPool2d(3, 2, 1), ChannelsLastMaxPool2d(3, 2, 1)):
        leaf = x.clone().requires_grad_(True)
        pool(leaf).square().sum().backward()
        grads.append(leaf.grad)
    assert torch.equal(grads[0], grads[1])
    assert ChannelsLastMaxPool2d(2, return_indices=True)(x)[1].dtype == torch.int64


@pytest.mark.parametrize("which", ["tiny", "shipped"])
def test_loaded_policies_pool_channels_last_and_their_actions_keep_their_bits(tmp_path, which):
    path = (make_tiny_diffusion_checkpoint(tmp_path / "tiny") if which == "tiny"
            else ROOT / "policy" / "pick_place_diffusion")
    quiet = lambda _: None  # noqa: E731
    fast = LeRobotPolicy(path, log=quiet)
    assert sum(isinstance(m, ChannelsLastMaxPool2d) for m in fast.policy.modules()) == 1
    plain = LeRobotPolicy(path, log=quiet)
    assert use_default_pooling(plain.policy) == 1
    assert use_channels_last_pooling(nn.Sequential(nn.ReLU())) == 0
    reqs = _requests(fast, 11)  # one full forward of 8 rows and one padded
    np.testing.assert_array_equal(_chunks(fast, reqs), _chunks(plain, reqs))


FAULTS = """
import resource, sys
sys.path.insert(0, {bench!r})
import numpy as np
if {keep}:
    from so101_sim.utils.heap import keep_freed_memory
    assert keep_freed_memory()
else:
    import so101_sim.utils.heap as heap
    heap.keep_freed_memory = lambda log=None: False  # glibc's default heap
import torch
torch.set_num_threads(1)
from so101_sim.harness.policies.lerobot import LeRobotPolicy
from bench_forward_rows import chunks as _chunks, requests as _requests
policy = LeRobotPolicy({ckpt!r}, log=lambda _: None)
reqs = _requests(policy, 8)
_chunks(policy, reqs); _chunks(policy, reqs)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
_chunks(policy, reqs); _chunks(policy, reqs)
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) // 2)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_policy_process_keeps_its_freed_memory_so_forwards_stop_page_faulting():
    ckpt = str(ROOT / "policy" / "pick_place_diffusion")
    faults = {}
    for keep in (True, False):
        out = subprocess.run([sys.executable, "-c", FAULTS.format(
            bench=str(ROOT / "benchmarks"), keep=keep, ckpt=ckpt)],
            capture_output=True, text=True, check=True)
        faults[keep] = int(out.stdout.split()[-1])
    # measured here: 0 kept, ~4,950 per 8-row forward on glibc's default heap
    assert faults[True] * 10 < faults[False], faults
