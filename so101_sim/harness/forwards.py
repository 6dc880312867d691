"""The eval loop's policy forwards: one at a time, or two at once on driver threads.

With cheap renders the driver's forwards are the bottleneck: one forward at a time keeps one
core on the policy while the env workers leave the other half idle. A policy that says its
``predict_chunks`` may run concurrently (``concurrent_forwards = True``: the lerobot adapter,
whose per-episode state is per slot and whose processor pipelines take turns) gets two
forwards in flight on a thread pool, each with the torch thread count the harness set, so
every row still sees the same kernels, batch size and threads as one forward at a time: the
actions are the same bit for bit. A finished forward writes a byte into a pipe the worker
pool waits on, so the loop wakes for it as it does for a worker's reply.
"""

from __future__ import annotations

import contextlib
import sys
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from multiprocessing import Pipe
from typing import Any

from so101_sim.harness.policies.protocol import core_to_spare
from so101_sim.utils.devices import cpu_count

CONCURRENT = 2  # forwards in flight when allowed: one per core of a 2-core machine


def _threads() -> int:
    torch = sys.modules.get("torch")
    return torch.get_num_threads() if torch is not None else 1


def _same_threads(n: int) -> None:
    """Give a forward thread the driver's torch thread count (OpenMP's is per thread)."""
    import torch

    torch.set_num_threads(n)


def forward_stats(peak: int = 0, used: int = 0, computed: int = 0) -> dict[str, Any]:
    """``eval_info.json``'s forward counts for one invocation: the most forwards in flight at
    once, and the policy rows asked for and computed (padding included)."""
    return {"forwards_in_flight": peak, "policy_rows": {"used": used, "computed": computed}}


class Forwards:
    """Forwards in flight; ``finished`` hands back (requests, tokens, actions, seconds).
    ``pad_to``: the policy pads every forward to a multiple of this many rows (0: no padding)."""

    def __init__(self, policy: Any, concurrent: bool, pad_to: int = 0) -> None:
        self.policy = policy
        self.limit = CONCURRENT if concurrent else 1
        self.inflight: list[tuple[Future, list, list, float]] = []
        self.peak = 0  # most forwards ever in flight at once
        self._pad_to = pad_to
        self.rows_used = 0
        self.rows_computed = 0
        self._executor: ThreadPoolExecutor | None = None
        self._wake_r: Any = None
        self._wake_w: Any = None
        # A forward alone may take a second core only where the forwards use half the cores or
        # less (every forward thread runs the driver's torch thread count).
        self._can_spare = 2 * _threads() <= cpu_count()
        if concurrent:
            self._executor = ThreadPoolExecutor(self.limit, thread_name_prefix="so101-forward",
                                                initializer=_same_threads,
                                                initargs=(_threads(),))
            self._wake_r, self._wake_w = Pipe(duplex=False)

    @property
    def wake(self) -> Any:
        """A handle that turns readable when a forward finishes (None: nothing in flight)."""
        return self._wake_r if self.inflight and self._executor is not None else None

    @staticmethod
    def pair_helps(envs: int, batch: int) -> bool:
        """Can a second forward in flight do anything? Only with more envs than one holds."""
        return envs > batch

    def can_launch(self) -> bool:
        return len(self.inflight) < self.limit

    def should_launch(self, waiting: int, batch: int, envs_stepping: bool) -> bool:
        """Launch a forward for the `waiting` rows now? When it is full; or when no env is
        stepping, since then no row can join it before a forward in flight ends: a free
        forward thread takes the short batch at once (padded, so every row's arithmetic is
        the same) rather than leave its core idle, as it would while fewer envs are live than
        two forwards hold, at the end of a run or with fewer envs than that."""
        if not waiting or not self.can_launch():
            return False
        return waiting >= batch or not envs_stepping

    def launch(self, requests: list, tokens: list, alone: bool = False) -> None:
        """Start a forward for `requests`; `tokens` come back with its actions. `alone`: no
        env is stepping, so with no other forward in flight this one may take a second core
        (harness.policies.encoder_split) while the driver waits for it."""
        t0 = time.perf_counter()
        n = len(requests)
        self.rows_used += n
        self.rows_computed += -(-n // self._pad_to) * self._pad_to if self._pad_to else n
        spare = alone and not self.inflight and self._can_spare
        if self._executor is None:
            fut: Future = Future()
            try:
                fut.set_result(self._timed(requests, spare))
            except BaseException as exc:  # raised again by finished(), as a sync call would
                fut.set_exception(exc)
        else:
            fut = self._executor.submit(self._timed, requests, spare)
            fut.add_done_callback(self._signal)
        self.inflight.append((fut, requests, tokens, t0))
        self.peak = max(self.peak, len(self.inflight))

    def stats(self) -> dict[str, Any]:
        return forward_stats(self.peak, self.rows_used, self.rows_computed)

    def _timed(self, requests: list, spare: bool) -> tuple[Any, float]:
        with core_to_spare(spare):
            return self.policy.predict_chunks(requests), time.perf_counter()

    def _signal(self, _: Future) -> None:
        with contextlib.suppress(OSError):  # closed: the loop is over
            self._wake_w.send_bytes(b".")

    def wait(self) -> None:
        """Block until a forward in flight finishes."""
        if self.inflight:
            wait([f for f, *_ in self.inflight], return_when=FIRST_COMPLETED)

    def finished(self) -> list[tuple[list, list, Any, float]]:
        """The forwards done so far, in launch order (a policy error is raised here)."""
        if self._wake_r is not None:
            while self._wake_r.poll():
                self._wake_r.recv_bytes()
        out = []
        for item in [x for x in self.inflight if x[0].done()]:
            self.inflight.remove(item)
            fut, requests, tokens, t0 = item
            actions, t_done = fut.result()
            out.append((requests, tokens, actions, t_done - t0))
        return out

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._wake_w.close()
            self._wake_r.close()
