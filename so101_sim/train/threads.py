"""Torch threads for the training loop on a CPU that other processes share.

`AdaptiveThreads` picks how a step uses the cores: on an idle machine one OpenMP pool over all
cores (torch's default, bitwise repeatable); with a neighbour busy, the batch is cut into parts
that run forward and backward in their own Python threads with one intra-op thread each
(`BatchParts`). A pool of OpenMP threads meets at a barrier after every parallel region, so
one thread that lost its core stalls the rest; independent parts do not wait for each other,
and the scheduler gives them whatever share of the cores the neighbours leave. Measured on 2
cores beside one busy process (benchmarks/bench_train_step.py --busy), against the idle 2-thread
step: a step at 2 OpenMP threads took 2.94x, at 1 thread 1.27x, in 2 parts 1.20x.
"""

from __future__ import annotations

import os
import statistics
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from so101_sim.utils.devices import cpu_count

MAX_PARTS = 8  # a batch of 32 in more parts than this gets GEMMs too small to be efficient


class CpuShare:
    """Cores that other processes kept busy since the last reading, from /proc/stat (Linux).

    The machine's busy time (user, nice, system, irq, softirq, steal) minus this process's own
    CPU time, over the wall time between readings. Only used where /proc/stat counts exactly
    the cores this process may run on: in a container on a bigger host it counts the host's
    other tenants, and `available()` says no.
    """

    def __init__(self) -> None:
        self._hz = os.sysconf("SC_CLK_TCK")
        self._last = self._read()

    @staticmethod
    def available(cores: int) -> bool:
        try:
            lines = Path("/proc/stat").read_text().splitlines()
        except OSError:
            return False
        per_cpu = [ln for ln in lines if ln.startswith("cpu") and ln[3:4].isdigit()]
        return len(per_cpu) == cores

    def _read(self) -> tuple[float, float, float]:
        with open("/proc/stat") as f:
            ticks = [int(x) for x in f.readline().split()[1:9]]
        busy = sum(ticks) - ticks[3] - ticks[4]  # all but idle and iowait; guest is in user
        return time.perf_counter(), busy / self._hz, time.process_time()

    @property
    def since(self) -> float:
        """perf_counter() of the last reading."""
        return self._last[0]

    def others(self) -> float:
        """Cores used by everything but this process since the last call (>= 0)."""
        (t0, busy0, own0), now = self._last, self._read()
        self._last = now
        wall = max(now[0] - t0, 1e-6)
        return max(0.0, ((now[1] - busy0) - (now[2] - own0)) / wall)


class AdaptiveThreads:
    """How a training step uses the CPU, fitted to the cores other processes leave.

    `current` is torch's intra-op thread count and `parts` the number of batch parts run in
    parallel threads (1: the whole batch on one OpenMP pool).

    On Linux (`CpuShare`) it reads, every `window_s` seconds, how many cores other processes
    used. While they leave all cores free (`margin` of a core allowed) it runs one pool over
    all cores; otherwise it cuts the batch into `min(cores, MAX_PARTS)` parts of one thread
    each, so that no step waits on a barrier for a thread without a core. No step is spent on
    a slow setting to find out. Parts draw their diffusion noise from torch's one generator
    in whatever order the threads get there, so a busy stretch is not bitwise repeatable (the
    draws are the same in distribution).

    Elsewhere (no /proc/stat) it keeps one pool and times the loop to pick its size: every
    `every` steps (and once the median of the last 4 x `probe` steps is 1.3x the last best) it
    times `probe` steps with each candidate (all cores, half, one; the first step after a
    switch is a warm-up) and keeps the fastest, probing half as often while the answer holds
    (up to every 4 x `every` steps). Thread count changes the float rounding of a step, so an
    adaptive run is exact on resume only where it made the same choices; pass a fixed
    ``--threads`` for bitwise repeatability.
    """

    def __init__(self, cores: int | None = None, every: int = 300, probe: int = 6,
                 first: int = 10, sense: bool = True, window_s: float = 2.0,
                 margin: float = 0.25) -> None:
        import torch

        self._torch = torch
        self.cores = cores or cpu_count()
        self.candidates = sorted({self.cores, max(1, self.cores // 2), 1}, reverse=True)
        self.share = CpuShare() if sense and CpuShare.available(self.cores) else None
        self.window_s, self.margin = window_s, margin
        self.every, self.probe, self.next_probe = every, probe, first
        self._gap = every // 2  # the first repeat of the first answer probes after `every`
        self.best_s: float | None = None
        # the slowdown check looks at a longer window than a probe, so that one slow step
        # (a checkpoint save, a neighbour's burst) does not set off a probe
        self.recent: deque[float] = deque(maxlen=4 * probe)
        self._trial: tuple[int, list[float], dict[int, float]] | None = None
        self.current = self.chosen = self.candidates[0]  # in force / picked by the last probe
        self.parts = 1
        torch.set_num_threads(self.current)

    def after_step(self, step: int, seconds: float) -> None:
        """Feed the duration of the step just done; may change the thread count."""
        if len(self.candidates) == 1:
            return
        if self.share is not None:
            if time.perf_counter() - self.share.since >= self.window_s:
                idle = self.share.others() <= self.margin
                self.parts = 1 if idle else min(self.cores, MAX_PARTS)
                self._set(self.cores if idle else 1)
            return
        if self._trial is None:
            self.recent.append(seconds)
            slow = (self.best_s is not None and len(self.recent) == self.recent.maxlen
                    and statistics.median(self.recent) > 1.3 * self.best_s)
            if step >= self.next_probe or slow:
                self._trial = (0, [], {})
                self._set(self.candidates[0])
            return
        i, times, results = self._trial
        times.append(seconds)
        if len(times) <= self.probe:
            return
        results[self.candidates[i]] = statistics.median(times[1:])
        if i + 1 < len(self.candidates):
            self._trial = (i + 1, [], results)
            self._set(self.candidates[i + 1])
            return
        best = min(results, key=results.__getitem__)
        # the same answer again: probe half as often (up to 4x `every`), since each probe
        # spends steps on the slower setting; a new answer: back to every `every` steps
        self._gap = min(2 * self._gap, 4 * self.every) if best == self.chosen else self.every
        self.best_s, self._trial, self.chosen = results[best], None, best
        self.next_probe = step + self._gap
        self.recent.clear()
        self._set(best)

    def _set(self, n: int) -> None:
        if n != self._torch.get_num_threads():
            self._torch.set_num_threads(n)
        self.current = n


def split_batch(batch: dict, parts: int) -> list[tuple[dict, float]]:
    """`batch` cut into up to `parts` slices along the sample axis, each with its share of it."""
    import torch

    n = next(v.shape[0] for v in batch.values() if isinstance(v, torch.Tensor) and v.ndim)
    out = []
    for ix in torch.tensor_split(torch.arange(n), min(parts, n)):
        lo, hi = int(ix[0]), int(ix[-1]) + 1
        out.append(({k: v[lo:hi] if isinstance(v, torch.Tensor) and v.ndim and v.shape[0] == n
                     else v for k, v in batch.items()}, (hi - lo) / n))
    return out


class BatchParts:
    """Forward and backward of one batch in `parts` threads, gradients summed in place.

    `loss_fn(part)` returns the mean loss over `part`'s samples. Each part back-propagates its
    loss times its share of the samples, so the summed gradients (and the returned loss) are
    the whole batch's; a batch in one part runs on the calling thread, unweighted, exactly as
    a plain `loss.backward()`. Autograd adds into `.grad` under a lock, so the parts can share
    the parameters. Threads are kept between steps; `close()` ends them.
    """

    def __init__(self) -> None:
        self._pool: ThreadPoolExecutor | None = None
        self._size = 0

    @staticmethod
    def _backward(loss_fn: Callable[[dict], Any], part: dict, weight: float) -> float:
        loss = loss_fn(part)
        (loss if weight == 1.0 else loss * weight).backward()
        return float(loss.detach()) * weight

    def __call__(self, loss_fn: Callable[[dict], Any], batch: dict, parts: int) -> float:
        """Back-propagate `loss_fn` over `batch`; returns the batch's mean loss."""
        if parts <= 1:
            return self._backward(loss_fn, batch, 1.0)
        if self._size != parts:
            self.close()
            self._pool, self._size = ThreadPoolExecutor(parts, "train-part"), parts
        futures = [self._pool.submit(self._backward, loss_fn, b, w)
                   for b, w in split_batch(batch, parts)]
        return sum(f.result() for f in futures)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
        self._pool, self._size = None, 0
