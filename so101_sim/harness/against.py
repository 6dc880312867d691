"""``so101-sim eval --against RUN``: rerun an earlier run's seeds in order, stop once decided.

Each finished episode is paired with RUN's outcome on the same seed and fed, in seed order, to
the anytime-valid sequential test of ``harness.sequential``. Episodes finish out of order on
several workers, so the test only ever sees the consecutive prefix of seeds from the first
one: the stopping rule depends on outcomes alone, never on which worker was faster. When it
decides, the run stops (episodes still running are dropped) and ``eval_info.json`` gets a
``sequential_verdict`` (verdict, episodes used, the statistic).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from shlex import quote
from typing import Any

from so101_sim.dataset import EVAL_SEED_START
from so101_sim.harness.compare import RunSide, load_run, seed_ranges, seen_render_size, setup_note
from so101_sim.harness.results import INFO
from so101_sim.harness.sequential import UNDECIDED, SequentialPairedTest, Verdict
from so101_sim.harness.suite import names_several_tasks
from so101_sim.utils.versions import setup_differences


class AgainstRun:
    """The ``stop`` hook of ``evaluate``: pairs finished episodes with RUN's, in seed order."""

    def __init__(self, reference: RunSide, margin: float = 0.0, indifference: float = 0.10,
                 alpha: float = 0.05, max_episodes: int | None = None) -> None:
        seeds = sorted(reference.success)
        if not seeds:
            raise ValueError(f"--against {reference.path}: the run holds no episodes")
        if seeds != list(range(seeds[0], seeds[0] + len(seeds))):
            raise ValueError(f"--against {reference.path}: its seeds are not consecutive "
                             f"({seed_ranges(seeds)}); {_gap_reason(reference.path)}")
        self.reference = reference
        self.seeds = seeds if max_episodes is None else seeds[:max_episodes]
        self.test = SequentialPairedTest(margin, indifference, alpha,
                                         max_episodes=len(self.seeds))
        self.result: Verdict | None = None
        self._next = 0  # index into self.seeds of the next pair the test has not seen

    def update(self, done: Mapping[int, Any]) -> bool:
        """Feed every newly available consecutive pair; True once the test has decided."""
        while self.result is None and self._next < len(self.seeds):
            seed = self.seeds[self._next]
            if seed not in done:
                break
            self._next += 1
            verdict = self.test.update(self.reference.success[seed], bool(done[seed].success))
            if verdict is not None:
                self.result = verdict
        return self.result is not None and self.result.verdict != "undecided"

    def verdict(self) -> Verdict:
        return self.result or self.test.verdict()

    def to_info(self) -> dict[str, Any]:
        return {**self.verdict().to_dict(), "against": str(self.reference.path),
                "reference_policy": self.reference.policy}


def reference_task(reference: RunSide, task: str | Path | None) -> str | Path:
    """The task to run against `reference`: `task` (a name or a .toml path, e.g. a task file
    outside envs/) when it is RUN's, RUN's task name when None; anything else is refused."""
    if task is None:
        return reference.task
    name = None
    if not names_several_tasks(task):  # a list of tasks is never one run's
        from so101_sim.tasks import load_task

        name = load_task(task).name
    if name != reference.task:
        raise ValueError(f"--task {task} given with --against {reference.path}, which was "
                         f"measured on {reference.task!r}: the paired test needs the same "
                         "task; drop --task, or pick a RUN of that task")
    return task


def check_out(run: str | Path, out: str | Path | None) -> None:
    """Refuse ``--out RUN``: the run would add its episodes to the reference it is tested
    against and write its verdict over RUN's eval_info.json."""
    if out is not None and Path(out).resolve() == Path(run).resolve():
        raise ValueError(f"--out {out} is the --against run itself: its episodes and verdict "
                         "would be written into the reference they are tested against; "
                         "choose another --out (or leave it out)")


def evaluate_against(policy: Any, run: str | Path, *, margin: float = 0.0,
                     indifference: float = 0.10, alpha: float = 0.05,
                     max_episodes: int | None = None, task: Any = None,
                     log: Callable[[str], None] = print, **evaluate_kwargs: Any
                     ) -> dict[str, Any]:
    """Evaluate `policy` on RUN's seeds (its task unless `task`) until the paired sequential
    test decides; returns the eval_info dict with ``sequential_verdict``."""
    from so101_sim.harness.runner import evaluate

    check_out(run, evaluate_kwargs.get("out_dir"))
    reference = load_run(run)
    task = reference_task(reference, task)
    stop = AgainstRun(reference, margin, indifference, alpha, max_episodes)
    for key in ("episodes", "seed_start"):
        if key in evaluate_kwargs:
            raise ValueError(f"--against takes its seeds from {run}; drop {key}")
    evaluate_kwargs.setdefault("allow_train_seeds", stop.seeds[0] < EVAL_SEED_START)
    result = evaluate(policy, task=task, episodes=len(stop.seeds),
                      seed_start=stop.seeds[0], stop=stop, log=log, **evaluate_kwargs)
    log(f"so101-sim eval: {stop.verdict().line()} against {run}")
    if hint := more_seeds_hint(stop, run):
        log(f"so101-sim eval: {hint}")
    if differences := setup_differences(reference.setup, result["config"]):
        log(f"so101-sim eval: {setup_note(differences)}")
    if note := render_note(reference, result["config"]):
        log(f"so101-sim eval: {note}")
    return result


def more_seeds_hint(stop: AgainstRun, run: str | Path) -> str | None:
    """How to go on when "undecided" came from running out of RUN's seeds (not from
    --max-episodes): a true drop near the indifference edge can need more than 200."""
    from so101_sim.utils.disk import resume_command

    verdict, n = stop.verdict(), len(stop.reference.success)
    if verdict.verdict != UNDECIDED or len(stop.seeds) < n or verdict.episodes < n:
        return None
    again = resume_command()  # an --against run resumes onto RUN's new seeds
    then = f"then {again}" if again else "then this evaluation again with resume=True"
    return (f"all {n} seeds of {run} ran without a decision; to go on, extend it: run its "
            f"eval command again with --out {quote(str(run))} --resume --episodes {2 * n} "
            f"(the {n} seeds already run are kept), {then} (its {n} episodes are kept too)")


def render_note(reference: RunSide, config: dict[str, Any]) -> str | None:
    """One line when this run's policy saw frames rendered at another size than RUN's: a
    closed-loop policy parts on small frame differences on some seeds (the shipped one on
    17 of 200 between 240x320 and 480x640, 18 between 180x240 and 480x640), which the test
    would put on the policy."""
    ours, theirs = seen_render_size(config), reference.render_size
    if ours is None or theirs is None or ours == theirs:
        return None
    same = ("--faithful" if reference.images.startswith("faithful")
            else f"--image-size {theirs[0]}x{theirs[1]}")
    return (f"note: {reference.path} rendered the cameras at {theirs[0]}x{theirs[1]}, this run "
            f"at {ours[0]}x{ours[1]}: frames differ slightly, and some seeds' outcomes may "
            f"differ for that reason alone, not the policy's; {same} renders as it did")


def _gap_reason(path: Path) -> str:
    """What to pass instead of a run with gaps, in the words of its own eval_info.json."""
    try:
        stopped = json.loads((path / INFO).read_text(encoding="utf-8")).get("sequential_verdict")
    except (OSError, ValueError, AttributeError):
        stopped = None
    if isinstance(stopped, dict):
        return (f"it is an `eval --against` run, stopped once its test decided (episodes still "
                f"running were dropped); pass a full `so101-sim eval` run instead, e.g. the one "
                f"it was measured against ({stopped.get('against', '?')})")
    return "expected one finished `so101-sim eval` run"
