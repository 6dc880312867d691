"""The mechanics under `so101-sim explain`: hooks that record what lerobot's modules see, a
stand-in for the random draws of `compute_loss`, and tensor look-ups that read a layout (where a
crop was taken, where a part sits in a vector) instead of assuming it."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch

from so101_sim.explain.errors import ExplainError


def tolist(t: Any) -> Any:
    """Tensor -> nested Python lists for JSON (floats as float32 values, bools as bools)."""
    if not isinstance(t, torch.Tensor):
        return t
    t = t.detach().cpu()
    return (t if t.dtype in (torch.bool, torch.int64, torch.int32) else t.float()).tolist()


# ----------------------------------------------------------------------------- hooks


class Hooks:
    """Forward hooks that record module inputs/outputs under a name; removed on exit."""

    def __init__(self) -> None:
        self.out: dict[str, Any] = {}
        self.calls: list[tuple[str, Any, Any]] = []
        self._handles: list[Any] = []

    def output(self, name: str, module: torch.nn.Module) -> None:
        self._handles.append(module.register_forward_hook(
            lambda _m, _a, o: self.out.__setitem__(name, o.detach().clone())))

    def input(self, name: str, module: torch.nn.Module) -> None:
        self._handles.append(module.register_forward_pre_hook(
            lambda _m, a: self.out.__setitem__(name, a[0].detach().clone())))

    def add(self, handle: Any) -> None:
        """Keep a handle of a hook registered elsewhere, to remove it on exit."""
        self._handles.append(handle)

    def every_call(self, name: str, module: torch.nn.Module) -> None:
        """Inputs (args + kwargs) and output of each call, in order."""
        def hook(_m: Any, args: tuple, kwargs: dict, out: Any) -> None:
            self.calls.append((name, (args, kwargs), out.detach().clone()))
        self._handles.append(module.register_forward_hook(hook, with_kwargs=True))

    def __enter__(self) -> Hooks:
        return self

    def __exit__(self, *exc: object) -> None:
        for h in self._handles:
            h.remove()


class FixedDraws:
    """Stands in for `torch` inside lerobot's modeling_diffusion for one `policy.forward`, so
    `compute_loss` uses our epsilon and step k instead of its `torch.randn`/`torch.randint`."""

    def __init__(self, eps: torch.Tensor, k: int) -> None:
        self.eps, self.k, self.calls = eps, k, {"randn": 0, "randint": 0}

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)

    def randn(self, *size: Any, **kwargs: Any) -> torch.Tensor:
        shape = tuple(size[0]) if len(size) == 1 and not isinstance(size[0], int) else size
        if tuple(shape) != tuple(self.eps.shape):
            raise ExplainError(f"compute_loss drew noise of shape {tuple(shape)}, expected "
                               f"{tuple(self.eps.shape)}; this lerobot is not supported")
        self.calls["randn"] += 1
        return self.eps.clone().to(kwargs.get("device") or self.eps.device)

    def randint(self, *args: Any, **kwargs: Any) -> torch.Tensor:
        size = kwargs.get("size", args[-1] if args else None)
        high = kwargs.get("high", args[1] if len(args) > 2 else args[0] if len(args) == 2 else None)
        if high is not None and not 0 <= self.k < int(high):
            raise ExplainError(f"--k {self.k} is outside the scheduler's 0..{int(high) - 1}")
        self.calls["randint"] += 1
        return torch.full(tuple(size), self.k, dtype=torch.long, device=kwargs.get("device"))


@contextlib.contextmanager
def fixed_draws(eps: torch.Tensor, k: int) -> Iterator[FixedDraws]:
    """Make lerobot's `DiffusionModel.compute_loss` use noise `eps` and timestep `k`; raises
    if it did not draw exactly one noise tensor and one timestep (a lerobot we do not know)."""
    from unittest import mock

    from lerobot.policies.diffusion import modeling_diffusion

    draws = FixedDraws(eps, k)
    with mock.patch.object(modeling_diffusion, "torch", draws):
        yield draws
    if draws.calls != {"randn": 1, "randint": 1}:
        raise ExplainError(f"compute_loss drew {draws.calls} instead of one noise tensor and "
                           "one timestep; this lerobot version is not supported by explain")


def find_slice(vector: torch.Tensor, piece: torch.Tensor, taken: set[int]) -> int | None:
    """Start of the first exact copy of `piece` in `vector` not already claimed, else None."""
    n = piece.numel()
    if n > vector.numel():
        return None
    hits = (vector.unfold(0, n, 1) == piece.reshape(1, n)).all(1).nonzero().flatten().tolist()
    free = [h for h in hits if not taken.intersection(range(h, h + n))]
    return free[0] if free else None


def crop_offset(image: torch.Tensor, crop: torch.Tensor) -> tuple[int, int] | None:
    """(top, left) where `crop` [C, h, w] sits inside `image` [C, H, W], read by comparison."""
    (_, h, w), (_, big_h, big_w) = crop.shape, image.shape
    for top in range(big_h - h + 1):
        for left in range(big_w - w + 1):
            if torch.equal(image[:, top:top + h, left:left + w], crop):
                return top, left
    return None
