"""The image encoder on two cores when a forward has one to spare: the same features, sooner.

A DDIM-10 forward of pick_place_diffusion spends about half its time in the ResNet-18 image
encoder (32 images for 8 rows: 2 cameras x 2 observation steps), on one thread. When a forward
starts with nothing else to do (no env stepping, no other forward in flight: evals with 8 or
fewer envs, the last episodes of a run), the other core idles until it ends. The harness
runs such a forward under ``protocol.core_to_spare(True)``, and its encoder cuts the batch in
two halves, the second on a helper thread. Forwards that start beside other work stay whole:
in a 16-env run, splitting whenever only one forward was in flight made the run 3% slower,
the half competing with the env workers for the core.

Exactness: on CPU a convolution's kernel, and so an image's bits, can change with the batch
size. The first time a batch of a new shape arrives, its halves are encoded as well and
compared with the whole batch; the split is used for that shape only if every feature is
bitwise equal (on this Xeon from 16 images up, not at 8 or 12), and never below
``MIN_HALF`` images a half. The helper runs with the caller's torch thread count. It is not
used with gradients on, in training mode, under autocast or off the CPU.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import torch
from torch import nn

from so101_sim.harness.policies.instance_forward import unwrap_forwards, wrap_forwards
from so101_sim.harness.policies.protocol import spare_core

__all__ = ["SplitEncoder", "use_split_encoder", "use_whole_encoder"]

MIN_HALF = 16  # images a half needs: below that the kernels changed bits in tests here


class SplitEncoder:
    """An image encoder's ``forward`` that encodes half its batch on a helper thread when
    ``spare()`` says a core is free and the halves were checked to give the same bits."""

    def __init__(self, encoder: nn.Module, spare: Callable[[], bool] = spare_core) -> None:
        self.encoder = encoder
        self.spare = spare
        self.splits = 0  # forwards that ran split (for tests and benchmarks)
        self._exact: dict[tuple, bool] = {}  # input signature -> halves keep the bits
        self._lock = threading.Lock()
        # Its thread starts at the first split; until then this costs nothing.
        self._helper = ThreadPoolExecutor(1, thread_name_prefix="so101-encoder")

    def whole(self, x: torch.Tensor) -> torch.Tensor:
        return type(self.encoder).forward(self.encoder, x)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if (x.shape[0] < 2 * MIN_HALF or x.shape[0] % 2 or self.encoder.training
                or torch.is_grad_enabled() or torch.is_autocast_enabled("cpu")
                or x.device.type != "cpu"):
            return self.whole(x)
        key = (tuple(x.shape), x.dtype, torch.get_num_threads())
        if key not in self._exact:
            with self._lock:
                if key not in self._exact:
                    out = self.whole(x)
                    self._exact[key] = torch.equal(out, self._split(x))
                    return out
        if not self._exact[key] or not self.spare():
            return self.whole(x)
        self.splits += 1
        return self._split(x)

    def _split(self, x: torch.Tensor) -> torch.Tensor:
        half = x.shape[0] // 2
        later = self._helper.submit(_encode, self.whole, x[half:], torch.get_num_threads())
        first = self.whole(x[:half])
        return torch.cat([first, later.result()])

    def close(self) -> None:
        self._helper.shutdown(wait=True)


def _encode(whole: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
            threads: int) -> torch.Tensor:
    # Grad mode and the OpenMP thread count are per thread: match the caller's.
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    with torch.no_grad():
        return whole(x)


ENCODER = "DiffusionRgbEncoder"  # lerobot's diffusion image encoder class


def use_split_encoder(module: nn.Module, spare: Callable[[], bool] = spare_core) -> int:
    """Run every diffusion image encoder inside `module` through ``SplitEncoder``; returns
    how many. Parameters are untouched, so weights and fingerprints stay what they were."""
    return wrap_forwards(module, ENCODER, SplitEncoder, lambda enc: SplitEncoder(enc, spare))


def use_whole_encoder(module: nn.Module) -> int:
    """Undo ``use_split_encoder`` (for A/B timings and tests); returns how many were undone."""
    removed = unwrap_forwards(module, ENCODER, SplitEncoder)
    for split in removed:
        split.close()
    return len(removed)
