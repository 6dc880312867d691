"""One policy on several tasks: ``so101-sim eval --task lift,stack`` or ``--task all``.

Each task is an ordinary evaluation in its own folder (``<out>/<task>/``: episodes.jsonl,
eval_info.json, videos, report), so ``--resume`` works per task. The suite folder's
``eval_info.json`` groups the results the way lerobot-eval groups a multi-task suite:
``per_task`` (one entry per task: ``task_group``, ``task_id``, ``metrics``), ``per_group``
(metrics by task name) and ``overall`` (all episodes pooled), with our Wilson interval and
failure modes added to each; one table is printed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from so101_sim.dataset import EVAL_SEED_START
from so101_sim.harness.stats import wilson_interval
from so101_sim.harness.trained_on import check_unseen_seeds
from so101_sim.tasks import available_tasks, load_task
from so101_sim.train.checkpoint import demos_of
from so101_sim.utils.atomic import write_json_atomic
from so101_sim.utils.disk import note_default_out

SUITE_INFO = "eval_info.json"


def names_several_tasks(task: str | Path) -> bool:
    """True for a --task that ``task_list`` reads as a list ("all" or "a,b"), not one task."""
    return "," in str(task) or str(task).strip() == "all"


def task_list(text: str) -> list[str]:
    """``"all"`` or comma-separated task names/paths -> task list; each one is checked."""
    names = available_tasks() if text.strip() == "all" else [
        t.strip() for t in text.split(",") if t.strip()]
    if not names:
        raise ValueError(f"--task {text!r} names no task; expected a name from "
                         f"{available_tasks()}, several separated by commas, or 'all'")
    if len(set(names)) != len(names):
        raise ValueError(f"--task {text!r} names a task twice; list each task once")
    for name in names:
        load_task(name)  # raises with the list of valid names
    return names


def evaluate_suite(policy: str, tasks: Sequence[str], *,
                   load_options: dict[str, Any] | None = None,
                   out_dir: str | Path | None = None, log: Callable[[str], None] = print,
                   **evaluate_kwargs: Any) -> dict[str, Any]:
    """Evaluate `policy` (``"expert"``, ``"baseline"``, a checkpoint or ``module:factory``) on each
    of `tasks` with the same seeds and settings; returns the suite's eval_info dict.

    `load_options` go to ``load_policy``; `evaluate_kwargs` (episodes, n_envs, seed_start,
    videos, image_size, resume, ...) to ``evaluate`` for every task.
    """
    from so101_sim.harness.policies import load_policy
    from so101_sim.harness.results import RunDir
    from so101_sim.harness.runner import evaluate

    if out_dir is None:
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        out_dir = Path("outputs/eval") / f"{Path(str(policy)).name}-suite-{stamp}"
        note_default_out(out_dir)  # the command that resumes it names this folder
    out = Path(out_dir)
    specs = [load_task(task) for task in tasks]
    if str(policy) == "baseline":  # only the tasks with shipped weights; say which are left out
        from so101_sim.harness.baselines import baselines

        shipped = {k for k, v in baselines().items() if "checkpoint" in v}
        left = [s.name for s in specs if s.name not in shipped]
        specs = [s for s in specs if s.name in shipped]
        if not specs:
            raise ValueError(f"--policy baseline: no weights are shipped for {left}; see "
                             "policy/baselines.toml for each task's card and recipe")
        if left:
            log(f"so101-sim eval: --policy baseline: no shipped weights for {left} (cards and "
                "recipes: policy/baselines.toml); evaluating the others")
    demos = demos_of(str(policy))  # {} for expert, baseline or module:factory
    if demos:  # rollout seeds it was trained on: refused before the first task runs
        start = evaluate_kwargs.get("seed_start", EVAL_SEED_START)
        seeds = range(start, start + evaluate_kwargs.get("episodes", 50))
        for spec in specs:
            check_unseen_seeds(demos, spec, seeds,
                               bool(evaluate_kwargs.get("allow_train_seeds")))
    for spec in specs:  # a forgotten --resume is said before the first policy loads
        RunDir(out / spec.name).check_target(bool(evaluate_kwargs.get("resume")))
    t0 = time.perf_counter()
    results: dict[str, dict[str, Any]] = {}
    for spec in specs:
        name = spec.name
        loaded = load_policy(policy, task=spec, **(load_options or {}))
        kwargs = dict(evaluate_kwargs)
        if kwargs.get("save_rollouts") is not None:  # one dataset per task: <DIR>/<task>
            kwargs["save_rollouts"] = Path(kwargs["save_rollouts"]) / name
        results[name] = evaluate(loaded, task=spec, out_dir=out / name, log=log, **kwargs)
    info = suite_info(results, time.perf_counter() - t0, out, str(policy))
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / SUITE_INFO, info)
    for line in suite_table(info):
        log(line)
    log(f"-> {out / SUITE_INFO}")
    return info


def suite_info(results: dict[str, dict[str, Any]], eval_s: float, out: Path,
               policy: str) -> dict[str, Any]:
    """lerobot-eval's multi-task layout (per_task / per_group / overall) from per-task runs."""
    per_task, per_group = [], {}
    episodes: list[dict[str, Any]] = []
    for name, result in results.items():
        metrics = {**result["aggregated"], "eval_dir": str(out / name)}
        per_task.append({"task_group": name, "task_id": 0, "metrics": metrics})
        per_group[name] = metrics
        episodes += result["per_episode"]
    n = len(episodes)
    k = sum(bool(e["success"]) for e in episodes)
    lo, hi = wilson_interval(k, n)
    mean = (lambda key: sum(e[key] for e in episodes) / n) if n else (lambda key: float("nan"))
    overall = {"pc_success": 100.0 * k / n if n else float("nan"),
               "success_ci95": [100.0 * lo, 100.0 * hi], "n_episodes": n, "n_success": k,
               "avg_sum_reward": mean("sum_reward"), "avg_max_reward": mean("max_reward"),
               "eval_s": eval_s, "eval_ep_s": eval_s / max(1, n)}
    first = next(iter(results.values()))["config"] if results else {}
    return {"per_task": per_task, "per_group": per_group, "overall": overall,
            "config": {"policy": policy, "tasks": list(results),
                       "seed_start": first.get("seed_start"),
                       "episodes": first.get("episodes")}}


def suite_table(info: dict[str, Any]) -> list[str]:
    """Markdown table: one row per task, then all tasks pooled."""
    lines = ["| task | success | 95% CI | failure modes | avg length | s/episode |",
             "| --- | --- | --- | --- | --- | --- |"]
    rows = [(e["task_group"], e["metrics"]) for e in info["per_task"]]
    for name, m in [*rows, ("all", info["overall"])]:
        lo, hi = m["success_ci95"]
        modes = ", ".join(f"{k} {v}" for k, v in m.get("failure_modes", {}).items())
        length = f"{m['avg_episode_len']:.0f}" if "avg_episode_len" in m else ""
        lines.append(f"| {name} | {m['n_success']}/{m['n_episodes']} = {m['pc_success']:.1f}% "
                     f"| {lo:.1f}-{hi:.1f} | {modes or ('none' if name != 'all' else '')} | "
                     f"{length} | {m['eval_ep_s']:.2f} |")
    return lines


def evaluate_suite_from_args(args: Any, load_options: dict[str, Any]) -> dict[str, Any]:
    """``so101-sim eval`` with several tasks: the same flags, applied to every task."""
    kwargs = {k: getattr(args, k) for k in ("episodes", "n_envs", "seed_start", "videos",
                                            "image_size", "resume", "allow_train_seeds",
                                            "backend", "ray_address", "save_rollouts",
                                            "threads", "faithful")
              if hasattr(args, k)}
    return evaluate_suite(args.policy, task_list(args.task), load_options=load_options,
                          out_dir=args.out, **kwargs)
