"""The recording loop: seeds out to workers, episodes into the spool, the dataset in seed order.

Workers (``so101_sim.workers``: local processes or Ray actors) simulate, render and encode
whole episodes; this process is the only writer. Each result is spooled as it arrives
(durable), then written into the dataset in seed order, with a checkpoint every
``checkpoint_every`` episodes and at the end (``so101_sim.dataset.store``). Seeds go out in
increasing order and only while the episodes kept so far plus those in flight are fewer than
wanted, so no surplus episode is recorded and the kept seeds are the same whatever the number
of workers or the backend. A seed already in the spool (a resumed run) is not simulated again.
"""

from __future__ import annotations

import shutil
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from so101_sim.dataset.interrupts import Interrupts
from so101_sim.dataset.schema import EVAL_SEED_START
from so101_sim.dataset.store import SCRATCH, Spool, crash_point, scratch, write_sidecar
from so101_sim.dataset.writer import Opened
from so101_sim.record.worker import RecorderSpec
from so101_sim.workers import start_pool

MAX_RETRIES = 2  # a seed whose worker died this many times more is an error

#: What the local fork server imports once for every recording worker: the env, the expert, and
#: lerobot's video encoder (which brings torch: most of the server's ~6 s of start-up).
WORKER_PRELOAD = ("so101_sim.record.worker", "lerobot.datasets.video_utils", "so101_sim.sim.env",
                  "so101_sim.expert")


@dataclass
class Tally:
    """Counts, sidecar and progress bar of one recording."""

    root: Path
    side: dict[str, Any]
    kept: int
    n_episodes: int
    progress: bool
    start_kept: int = 0
    successes: int = 0
    tried: int = 0
    env_steps: int = 0
    time_physics: float = 0.0
    time_render: float = 0.0
    time_write: float = 0.0  # wall time in the writers: encoding, spool, save_episode
    cpu_seconds: float = 0.0
    reused: int = 0  # episodes taken from the spool (finished before a kill), not simulated
    worker_start_s: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    bar: Any = None

    def __post_init__(self) -> None:
        self.start_kept = self.kept
        if self.progress:
            from tqdm import tqdm
            self.bar = tqdm(total=self.n_episodes, initial=self.kept, unit="ep", desc="record")

    def episode(self, meta: dict[str, Any], saved: bool) -> None:
        """Account for one episode written (or discarded) in seed order."""
        self.kept += saved
        self.successes += meta["success"]
        self.tried += 1
        self.env_steps += meta["steps"]
        for key in ("time_physics", "time_render", "time_write", "cpu_seconds"):
            setattr(self, key, getattr(self, key) + meta.get(key, 0.0))
        if not meta["success"]:
            self.side["failures"][str(meta["seed"])] = meta["failure_mode"]
        self.side["tried"].append(meta["seed"])
        write_sidecar(self.root, self.side)
        if self.bar is not None:
            self.bar.update(self.kept - self.bar.n)
            dt = time.perf_counter() - self.t0
            self.bar.set_postfix(success=f"{self.successes}/{self.tried}",
                                 steps_s=f"{self.env_steps / max(dt, 1e-9):.1f}")

    def summary(self, workers: int, backend: str) -> dict[str, Any]:
        dt = time.perf_counter() - self.t0
        return {"episodes": self.kept, "new_episodes": self.kept - self.start_kept,
                "successes": self.successes, "tried": self.tried,
                "failures": self.side["failures"], "env_steps": self.env_steps, "seconds": dt,
                "steps_per_s": self.env_steps / max(dt, 1e-9), "workers": workers,
                "backend": backend, "dart_noise": self.side["dart_noise"],
                "vcodec": self.side["vcodec"], "time_physics": self.time_physics,
                "time_render": self.time_render, "time_write": self.time_write,
                "cpu_seconds": self.cpu_seconds, "reused": self.reused,
                "worker_start_s": self.worker_start_s}


@dataclass
class Dispatcher:
    """Hands out seeds in increasing order and releases results in that order.

    A seed goes out only while ``kept + in flight < wanted``: even if every episode in flight
    succeeds, nothing surplus is recorded, so the kept seeds equal a one-worker run's.
    """

    next_seed: int
    window: int  # at most this many seeds running or queued in workers
    keep_failures: bool
    in_flight: list[int] = field(default_factory=list)  # dispatched, in order, not yet written
    done: dict[int, dict[str, Any]] = field(default_factory=dict)  # arrived, not yet written

    def to_send(self, kept: int, wanted: int) -> list[int]:
        will_keep = kept + sum(self.keep(m) for m in self.done.values())
        pending = len(self.in_flight) - len(self.done)
        seeds = []
        while pending < self.window and will_keep + pending < wanted and not self.exhausted:
            seeds.append(self.next_seed)
            self.in_flight.append(self.next_seed)
            self.next_seed += 1
            pending += 1
        return seeds

    @property
    def exhausted(self) -> bool:
        """No training seed is left to send (the expert failed some on the way)."""
        return self.next_seed >= EVAL_SEED_START

    def keep(self, meta: dict[str, Any]) -> bool:
        return bool(meta["success"] or self.keep_failures)

    def usable(self, meta: dict[str, Any] | None) -> bool:
        """A spooled episode stands for a run of its seed if it has what will be written."""
        return meta is not None and (meta["has_data"] or not self.keep(meta))

    def arrived(self, meta: dict[str, Any]) -> None:
        self.done[meta["seed"]] = meta

    def ready(self) -> Iterator[dict[str, Any]]:
        """Arrived results whose lower seeds are all written, lowest first."""
        while self.in_flight and self.in_flight[0] in self.done:
            yield self.done.pop(self.in_flight.pop(0))


def record_episodes(opened: Opened, tally: Tally, spec: RecorderSpec, workers: int,
                    backend: str, ray_address: str | None, checkpoint_every: int,
                    description: str) -> None:
    """Record until `tally` has its episodes; on any exit the dataset is left finalized at a
    checkpoint (Ctrl-C, SIGTERM) or recoverable by ``--resume`` (anything harsher)."""
    root = opened.root
    spool = Spool(root)
    spool.drop(s for s in spool.seeds() if s < opened.next_seed)  # already checkpointed
    dispatch = Dispatcher(opened.next_seed, 2 * workers, spec.keep_failures)
    deaths: Counter[int] = Counter()
    since_checkpoint, finished, writing = 0, False, False
    interrupts = Interrupts()
    pool = None

    def write_ready() -> None:
        nonlocal since_checkpoint, writing
        for meta in dispatch.ready():
            with interrupts.deferred():
                writing = True  # an error from here on may leave lerobot's writer mid-episode
                t = time.perf_counter()
                keep = dispatch.keep(meta)
                if keep:
                    opened.write(spool.load(meta["seed"]), description, spec.image_size)
                meta["time_write"] = meta.get("time_write", 0.0) + time.perf_counter() - t
                tally.episode(meta, keep)
                since_checkpoint += 1
                if since_checkpoint >= checkpoint_every and tally.kept < tally.n_episodes:
                    opened.checkpoint(reopen=True)
                    spool.drop(s for s in spool.seeds() if s <= meta["seed"])
                    since_checkpoint = 0
                writing = False

    interrupts.install()
    with scratch(root):
        try:
            pool = start_pool(spec, workers, backend=backend, ray_address=ray_address,
                              name="so101-record-worker",
                              preload=WORKER_PRELOAD)
            tally.worker_start_s = pool.start_s
            while True:
                interrupts.check()  # a Ctrl-C lost in a garbage-collection callback
                for seed in dispatch.to_send(tally.kept, tally.n_episodes):
                    meta = spool.meta(seed)
                    if dispatch.usable(meta):
                        dispatch.arrived(meta)
                        tally.reused += 1
                    else:
                        pool.submit(pool.least_busy(), "record", seed)
                write_ready()
                if not dispatch.in_flight:
                    if tally.kept >= tally.n_episodes:
                        break
                    if dispatch.exhausted:  # every episode run so far is written: say so
                        raise ValueError(
                            f"the training seeds ran out (the last is {EVAL_SEED_START - 1}) "
                            f"with {tally.kept} of {tally.n_episodes} episodes in {root}: the "
                            "expert failed some seeds. The dataset keeps them: train on it as "
                            "it is, or record the rest into another --out with a lower "
                            "--seed-start")
                    continue  # spooled episodes filled the window: send the next seeds
                if not pool.busy:
                    raise RuntimeError(f"seeds {dispatch.in_flight} are neither running nor "
                                       "spooled (a bug in so101-sim: please report it)")
                for reply in pool.collect():
                    seed = reply.args[0]
                    if reply.died:
                        deaths[seed] += 1
                        if deaths[seed] > MAX_RETRIES:
                            raise RuntimeError(f"recording seed {seed}: its worker died "
                                               f"{deaths[seed]} times; last: {reply.died}")
                        pool.submit(pool.least_busy(), "record", seed)  # run it again
                        continue
                    if reply.error:
                        raise RuntimeError(f"recording worker failed on seed {seed}:\n"
                                           f"{reply.error}")
                    with interrupts.deferred():
                        spool.put(reply.value)
                    crash_point("spooled")
                    dispatch.arrived(spool.meta(seed))
            finished = True
        finally:
            interrupts.ignore()
            try:
                if pool is not None:
                    pool.close()
                if not writing:  # else the writer may be mid-episode: leave it to recovery
                    write_ready()  # episodes that arrived in order before an interrupt
                    opened.checkpoint(reopen=False)
                    shutil.rmtree(root / SCRATCH, ignore_errors=True)
                if finished:
                    spool.remove()
                if tally.bar is not None:
                    tally.bar.close()
            finally:
                interrupts.restore()
