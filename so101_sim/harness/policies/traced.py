"""The diffusion U-Net's forward as a traced graph: the same ATen calls, without Python between.

A DDIM-10 forward of pick_place_diffusion calls the U-Net ten times, and each call runs about
a hundred small modules (8 rows, a horizon of 16), so a good part of each call is Python:
module dispatch, einops, argument handling (benchmarks/README.md: an 8-row forward on one
thread took 153.5 ms traced against 166.2 ms eager here). ``torch.jit.trace`` records the ATen
operations one eager call makes, and running that record calls the same operations with the
same arguments, so the outputs are the eager ones bit for bit. The graph runs with
TorchScript's optimisations off (``torch.jit.optimized_execution(False)``, a per-thread
switch), so no pass may rewrite, reorder or fuse an operation; what runs is exactly what was
recorded.

The eager forward still runs whenever the record might not be what eager would do: with
gradients on, in training mode, under autocast (``--precision bf16``), off the CPU, or when
the inputs' shapes or dtypes differ from every traced call so far (each new signature is
traced once, under a lock, so the two forward threads of an eval can share the policy).
The U-Net keeps its parameters and names; only its instance ``forward`` is replaced.

Why TorchScript, which torch 2.11 marks deprecated: of torch's graph capturers it is the one
that removes the Python and keeps the bits. ``torch.export``'s graph module ran at eager speed
(164 against 165 ms), and ``torch.compile`` (inductor) fuses the pointwise operations, which
moved the actions by up to 2e-5 and took 171 ms after a 41 s compile. Should a later torch
drop or refuse the trace, the eager U-Net runs, with one printed line.
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from so101_sim.harness.policies.instance_forward import unwrap_forwards, wrap_forwards

__all__ = ["TracedForward", "use_eager_unet", "use_traced_unet"]


class _EagerCall(nn.Module):
    """What gets traced: the U-Net's own class forward, with the conditioning as an input."""

    def __init__(self, unet: nn.Module) -> None:
        super().__init__()
        self.unet = unet

    def forward(self, x: torch.Tensor, timestep: torch.Tensor,
                global_cond: torch.Tensor | None) -> torch.Tensor:
        return type(self.unet).forward(self.unet, x, timestep, global_cond=global_cond)


class TracedForward:
    """A U-Net's ``forward`` that runs a traced record of itself where that is exact."""

    def __init__(self, unet: nn.Module, log: Callable[[str], None] = print) -> None:
        self.unet = unet
        self.log = log
        self._call = _EagerCall(unet)  # what is traced, and what runs eagerly
        self._graphs: dict[tuple, Any] = {}  # input signature -> traced graph (None: eager)
        self._lock = threading.Lock()

    def eager(self, x: torch.Tensor, timestep: torch.Tensor,
              global_cond: torch.Tensor | None = None) -> torch.Tensor:
        return self._call.forward(x, timestep, global_cond)

    def __call__(self, x: torch.Tensor, timestep: torch.Tensor,
                 global_cond: torch.Tensor | None = None) -> torch.Tensor:
        args = (x, timestep, global_cond)
        if (global_cond is None or self.unet.training or torch.is_grad_enabled()
                or torch.is_autocast_enabled("cpu")
                or any(a.device.type != "cpu" for a in args)):
            return self.eager(*args)
        key = tuple((tuple(a.shape), a.dtype) for a in args)
        if key not in self._graphs:
            with self._lock:
                if key not in self._graphs:
                    self._graphs[key] = self._trace(args)
        graph = self._graphs[key]
        if graph is None:
            return self.eager(*args)
        with torch.jit.optimized_execution(False):
            return graph(*args)

    def _trace(self, args: tuple[torch.Tensor, ...]) -> Any:
        try:
            with warnings.catch_warnings():  # shapes read as numbers; TorchScript's deprecation
                warnings.simplefilter("ignore", torch.jit.TracerWarning)
                warnings.simplefilter("ignore", DeprecationWarning)
                return torch.jit.trace(self._call, args, check_trace=False)
        except Exception as exc:  # a torch without TorchScript, or a U-Net it cannot record
            self.log(f"so101-sim eval: note: could not trace the diffusion U-Net "
                     f"({type(exc).__name__}: {str(exc)[:120]}); running it eagerly (the same "
                     "actions, slower forwards)")
            return None


UNET = "DiffusionConditionalUnet1d"  # lerobot's diffusion U-Net class


def use_traced_unet(module: nn.Module, log: Callable[[str], None] = print) -> int:
    """Run every diffusion U-Net inside `module` through ``TracedForward``; returns how many.

    Parameters are untouched, so a checkpoint's weights and fingerprint stay what they were.
    """
    return wrap_forwards(module, UNET, TracedForward, lambda unet: TracedForward(unet, log))


def use_eager_unet(module: nn.Module) -> int:
    """Undo ``use_traced_unet`` (for A/B timings and tests); returns how many were undone."""
    return len(unwrap_forwards(module, UNET, TracedForward))
