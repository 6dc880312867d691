"""``so101-sim eval --save-rollouts DIR``: every evaluated episode into a LeRobotDataset.

The env workers tape each episode (``rollout_tape``: every step rendered at the eval's render
size, both cameras encoded to mp4 in the worker). Here, in the driver, the pieces of
``record`` do the rest, so a rollout dataset is as durable as a recorded one: a finished
episode is spooled (``dataset.store.Spool``) *before* its line goes into episodes.jsonl, then
written through lerobot's ``save_episode`` in seed order (``dataset.writer.Opened``), with a
checkpoint every ``checkpoint_every`` episodes and at the end. Ctrl-C / SIGTERM end with a
finalized dataset; after a SIGKILL, ``eval --resume`` recovers the last checkpoint, writes
the spooled episodes and runs the rest, so every seed is in the dataset exactly once.

Columns (``rollout_features``): ``observation.state``, ``action`` (as executed: after the env's
clip to the joint limits), ``observation.images.<camera>`` (video), ``episode_seed``,
``initial_cube_pose`` (as ``record`` writes them), lerobot-eval's per-step ``next.reward``,
``next.success``, ``next.done``, and the episode's outcome on every frame:
``episode_success`` (bool) and ``episode_failure_mode`` (string, "" for none).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from so101_sim.dataset.schema import rollout_features
from so101_sim.harness.rollout_tape import TapeSpec
from so101_sim.tasks import TaskSpec

ROLLOUTS_KIND = "so101-sim eval --save-rollouts"
DEFAULT_REPO_ID = "local/so101_eval_rollouts"
CHECKPOINT_EVERY = 50


def check_resume_target(out: Path, config_path: Path, save_rollouts: str | None) -> None:
    """Refuse ``--resume`` with another ``--save-rollouts`` than the run started with (its
    finished episodes would be missing from the new folder, or never recorded)."""
    try:
        old = json.loads(config_path.read_text(encoding="utf-8")).get("save_rollouts")
    except (OSError, ValueError, AttributeError):
        return  # no config yet, or a corrupt one: RunDir.prepare says so
    if old == save_rollouts:
        return
    if old is None:
        raise ValueError(f"cannot resume {out} with --save-rollouts {save_rollouts}: that run "
                         "was started without --save-rollouts, so its finished episodes were "
                         "never recorded; finish it without --save-rollouts, or evaluate into "
                         "a new --out with --save-rollouts")
    flag = "without --save-rollouts" if save_rollouts is None else \
        f"with --save-rollouts {save_rollouts}"
    raise ValueError(f"cannot resume {out} {flag}: that run saves its rollouts to {old}; "
                     f"resume with --save-rollouts {old}")


def _started_here(root: Path) -> bool:
    """A folder a run killed before its first checkpoint leaves (no episode in it: starting
    afresh loses nothing)."""
    from so101_sim.dataset.store import COMMIT, SCRATCH, SIDECAR, SPOOL
    from so101_sim.utils.locks import LOCK_FILE

    ours = {"meta", "data", "videos", SIDECAR, COMMIT, SPOOL, SCRATCH, LOCK_FILE}
    return (not (root / COMMIT).exists() and all(p.name in ours for p in root.iterdir())
            and not any(p.is_file() for sub in ("data", "videos") for p in (root / sub).rglob("*")))


class RolloutSink:
    """The rollout dataset of one evaluation: checked, opened (or recovered), filled in seed
    order. `side` is its sidecar (``so101_sim_recording.json``: what ``replay`` reads, and
    the evaluation it belongs to)."""

    def __init__(self, root: Path, seeds: list[int], spec: TaskSpec, side: dict[str, Any],
                 image_size: tuple[int, int], checkpoint_every: int) -> None:
        self.root = root
        self.seeds = seeds
        self.spec = spec
        self.side = side
        self.image_size = image_size
        self.checkpoint_every = checkpoint_every
        self.opened: Any = None
        self.spool: Any = None
        self.stored: set[int] = set()
        self.next = 0  # index in `seeds` of the next episode to write
        self.since_checkpoint = 0
        self.writing = False
        self.tape: TapeSpec | None = None
        self._stack = ExitStack()
        self.interrupts: Any = None

    # ----------------------------------------------------------------------- open
    def check(self, resume: bool) -> bool:
        """Refuse a folder that is not this run's (before anything is written); return
        whether it holds this run's dataset to resume."""
        from so101_sim.dataset.store import read_sidecar
        from so101_sim.utils.locks import has_content

        root = self.root
        if root.exists() and not root.is_dir():
            raise ValueError(f"--save-rollouts {root} is a file; expected a folder for the "
                             "rollout dataset (a new one, or this run's when resuming)")
        if not has_content(root) or (resume and _started_here(root)):
            return False
        if not resume:
            raise ValueError(f"--save-rollouts {root} already exists and is not empty; expected "
                             "a new (or empty) folder for this evaluation's rollouts: choose "
                             "another --save-rollouts, or delete that folder")
        why = self._foreign(read_sidecar(root), self.side)
        if why:
            raise ValueError(f"--save-rollouts {root} is not this run's rollout dataset "
                             f"({why}); resume with the folder this evaluation was started "
                             "with, or evaluate into a new --out and --save-rollouts")
        return True

    def open(self, resume: bool) -> None:
        """Create the dataset, or bring it back to its last checkpoint (``--resume``)."""
        from so101_sim.dataset.interrupts import Interrupts
        from so101_sim.dataset.reader import info_features, stored_seeds
        from so101_sim.dataset.schema import DEFAULT_VCODEC, ROBOT_TYPE
        from so101_sim.dataset.store import (
            RecoveryError,
            Spool,
            checkpoint,
            read_sidecar,
            recover,
            scratch,
            write_sidecar,
        )
        from so101_sim.dataset.writer import Opened, encoder_config
        from so101_sim.utils.video_backend import quiet_libav

        quiet_libav()
        root, spec = self.root, self.spec
        if self.check(resume):
            if recover(root) is None:
                raise RecoveryError(f"--save-rollouts {root} has no checkpoint although it "
                                    "holds data; it cannot be resumed: evaluate into a new "
                                    "--out and --save-rollouts")
            self.side = read_sidecar(root)
            encoder = encoder_config(self.side["vcodec"], info_features(root))
        else:
            from so101_sim.dataset.writer import create_dataset
            from so101_sim.utils.locks import clear_folder

            if root.exists():  # empty, or a start killed before its first checkpoint
                clear_folder(root)  # (its lock file stays: this run holds it)
            root.mkdir(parents=True, exist_ok=True)
            self.side = {**self.side, "vcodec": DEFAULT_VCODEC}
            encoder = encoder_config(DEFAULT_VCODEC)
            create_dataset(root, repo_id=self.side["repo_id"], fps=spec.fps,
                           robot_type=ROBOT_TYPE, use_videos=True, rgb_encoder=encoder,
                           features=rollout_features(self.image_size, spec.cameras))
            write_sidecar(root, self.side)
            checkpoint(root, self.side)  # the empty dataset: what a kill before any episode
        stored = stored_seeds(root)
        if stored != self.seeds[:len(stored)]:
            raise ValueError(f"--save-rollouts {root} holds the episodes of seeds "
                             f"{stored[:3]}...; expected seeds from {self.seeds[0]} in order: "
                             "it is not this run's rollout dataset; evaluate into a new --out "
                             "and --save-rollouts")
        self.stored, self.next = set(stored), len(stored)
        self.spool = Spool(root)
        self.spool.drop(s for s in self.spool.seeds() if s in self.stored)
        self._stack.enter_context(scratch(root))
        self.interrupts = Interrupts()
        self.interrupts.install()
        self._stack.callback(self.interrupts.restore)
        self.opened = Opened(root, self.side, 0, dataclasses.asdict(encoder),
                             repo_id=self.side["repo_id"], encoder=encoder,
                             queue_size=spec.max_steps + 2)
        self.opened.reopen()
        self.tape = TapeSpec(tuple(spec.cameras), self.opened.encoder_kwargs,
                             spec.max_steps + 2)

    @staticmethod
    def _foreign(old: dict[str, Any], side: dict[str, Any]) -> str:
        """Why `old` (a folder's sidecar) is not the sidecar of this run, or ""."""
        if old.get("kind") != ROLLOUTS_KIND:
            return "it was not written by so101-sim eval --save-rollouts"
        for key in ("eval_out", "eval"):
            if old.get(key) != side[key]:
                return f"{key}: {old.get(key)!r} there, {side[key]!r} now"
        return ""

    # ----------------------------------------------------------------------- fill
    def has(self, seed: int) -> bool:
        """The episode of `seed` is in the dataset or spooled (no need to run it again)."""
        return seed in self.stored or self.spool.meta(seed) is not None

    def add(self, result: dict[str, Any], commit: Callable[[], None]) -> None:
        """Spool a worker's taped episode, then `commit` (its episodes.jsonl line), then write
        every episode that is next in seed order. Signals wait until the spool and the line
        are both on disk."""
        from so101_sim.dataset.store import crash_point

        with self.interrupts.deferred():
            self.spool.put(result)
            crash_point("rollout_spooled")
            commit()
        self.flush()

    def flush(self) -> None:
        """Write spooled episodes that are next in seed order; checkpoint every N."""
        while self.next < len(self.seeds) and self.spool.meta(self.seeds[self.next]):
            seed = self.seeds[self.next]
            with self.interrupts.deferred():
                self.writing = True  # an error from here may leave lerobot's writer mid-episode
                self.opened.write(self.spool.load(seed), self.spec.description,
                                  self.image_size)
                self.stored.add(seed)
                self.next += 1
                self.since_checkpoint += 1
                if self.since_checkpoint >= self.checkpoint_every and self.next < len(self.seeds):
                    self.opened.checkpoint(reopen=True)
                    self.spool.drop(s for s in self.spool.seeds() if s in self.stored)
                    self.since_checkpoint = 0
                self.writing = False

    def close(self, finished: bool) -> None:
        """Finalize and checkpoint (unless a write was cut mid-episode: then recovery on
        ``--resume`` does it); drop the spool once every seed is in the dataset."""
        from so101_sim.dataset.store import SCRATCH

        if self.interrupts is not None:
            self.interrupts.ignore()
        try:
            if self.opened is not None and self.opened.ds is not None and not self.writing:
                self.flush()
                self.opened.checkpoint(reopen=False)
                self.opened.ds = None
                shutil.rmtree(self.root / SCRATCH, ignore_errors=True)
                if finished and self.next == len(self.seeds):
                    self.spool.remove()
        finally:
            self._stack.close()


def rollout_sink(save_rollouts: str | Path, *, resume: bool, spec: TaskSpec, task_arg: str,
                 image_size: tuple[int, int], seeds: list[int], eval_out: Path,
                 identity: dict[str, Any], checkpoint_every: int = CHECKPOINT_EVERY,
                 repo_id: str = DEFAULT_REPO_ID) -> RolloutSink:
    """The rollout dataset of the evaluation `identity` in `eval_out`, checked but not opened
    yet (``open``). `task_arg` is stored for ``so101-sim replay`` (a task name or .toml)."""
    if not isinstance(checkpoint_every, int) or checkpoint_every < 1:
        raise ValueError(f"checkpoint_every={checkpoint_every!r} is invalid; expected an "
                         "integer >= 1 (episodes between rollout-dataset checkpoints)")
    from so101_sim.utils.versions import installed

    mujoco = installed("mujoco")  # what ``replay`` compares with the one re-simulating
    side = {"kind": ROLLOUTS_KIND, "repo_id": repo_id, "task": task_arg,
            "image_size": list(image_size), "fps": spec.fps,
            "eval_out": str(Path(eval_out).resolve()),
            "eval": json.loads(json.dumps(identity, default=list)),
            **({"mujoco": mujoco} if mujoco else {})}
    sink = RolloutSink(Path(save_rollouts), seeds, spec, side, image_size, checkpoint_every)
    sink.check(resume)
    return sink


def open_sink(sink: RolloutSink, resume: bool) -> None:
    """``sink.open``, releasing what it took if it fails."""
    try:
        sink.open(resume)
    except BaseException:
        sink._stack.close()
        raise
