"""Success against training progress: evaluate a run's saved checkpoints on evaluation seeds.

``so101-sim curve RUN --episodes 32 [--task T]`` runs the harness on each ``checkpoints/step_*/
pretrained_model`` of a `so101-sim train` run (every one, or every `--every` steps), on the
same seeds each time, and appends one line per checkpoint and task to ``RUN/eval_curve.jsonl``
(task, step, CPU-hours of training so far, successes, Wilson interval). A multi-task run has one
curve per task. Inference settings other than the checkpoint's own (``--temporal-ensemble``)
make a separate curve: its rows carry ``variant`` (e.g. ``temporal_ensemble_coeff=0.01``) and
its evaluations go to ``eval_curve/<task>-<variant>/``. Checkpoints already in the file
are skipped, so it can be rerun as training goes on. ``plot_curve`` draws it (success with
its interval against step and against training hours) for the model card.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from shlex import quote
from typing import Any

from so101_sim.dataset.interrupts import Interrupts
from so101_sim.harness.stats import wilson_interval
from so101_sim.tasks import DEFAULT_TASK
from so101_sim.train.checkpoint import read_train_info
from so101_sim.utils.atomic import append_line
from so101_sim.utils.locks import folder_lock

CURVE_FILE = "eval_curve.jsonl"
CURVE_LOCK = ".so101-curve.lock"  # not train's lock: a curve may run while training goes on
_STEP = re.compile(r"step_(\d+)$")


def run_checkpoints(run: Path) -> list[tuple[int, Path]]:
    """(step, pretrained_model dir) of every saved checkpoint of a training run, by step."""
    found = []
    for d in (run / "checkpoints").glob("step_*"):
        m = _STEP.search(d.name)
        if m and (d / "pretrained_model" / "model.safetensors").is_file():
            found.append((int(m.group(1)), d / "pretrained_model"))
    return sorted(found)


def curve_variant(policy_options: dict[str, Any] | None) -> str:
    """The label of a curve evaluated with these inference settings ("" = the checkpoint's)."""
    return ",".join(f"{k}={v}" for k, v in sorted((policy_options or {}).items()))


def read_curve(run: Path, task: str | None = None,
               variant: str | None = "") -> list[dict[str, Any]]:
    """The run's curve rows by step; only `task`'s if given (rows written before curves had a
    task are pick_place's, the only task then), and only `variant`'s (default: the
    checkpoint's own settings; None: every variant)."""
    path = run / CURVE_FILE
    if not path.is_file():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue  # a line torn by a kill: that checkpoint is evaluated again
    if task is not None:
        rows = [r for r in rows if r.get("task", DEFAULT_TASK) == task]
    if variant is not None:
        rows = [r for r in rows if r.get("variant", "") == variant]
    return sorted(rows, key=lambda r: r["step"])


def _not_a_run(path: Path) -> str:
    """Why `path` has no curve to draw, naming the run folder above a checkpoint given."""
    if not path.exists():
        return "does not exist"
    run = next((p for p in path.parents[:3] if run_checkpoints(p)), None)
    if run is not None:
        return (f"is one checkpoint of the run {run} (did you mean `so101-sim curve "
                f"{quote(str(run))}`?)")
    return "holds no checkpoints/step_*/pretrained_model"


def evaluate_curve(run: str | Path, *, episodes: int = 32, every: int = 0, n_envs: int = 16,
                   seed_start: int = 100_000, steps: list[int] | None = None,
                   task: str = DEFAULT_TASK, progress: bool = True,
                   policy_options: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Evaluate the run's checkpoints not yet in its curve file; return the whole curve.
    `policy_options` (``load_policy``'s, e.g. ``temporal_ensemble_coeff``) make a separate
    curve. Two curves of one run at once are refused (a training run may go on beside it)."""
    run = Path(run)
    checkpoints = run_checkpoints(run)
    if not checkpoints:
        raise ValueError(f"{run} {_not_a_run(run)}; pass the --out folder of a `so101-sim "
                         "train` run")
    check_choice(run, [s for s, _ in checkpoints], every, steps)
    with folder_lock(run, "the learning curve", again="rerun", name=CURVE_LOCK):
        _evaluate_missing(run, checkpoints, episodes, every, n_envs, seed_start, steps, task,
                          progress, policy_options or {})
    return [r for r in read_curve(run, task, curve_variant(policy_options))
            if r.get("episodes") == episodes and r.get("seed_start") == seed_start]


def check_choice(run: Path, saved: list[int], every: int, steps: list[int] | None) -> None:
    """Refuse an `every` or `steps` that picks none of the `saved` steps, or a step that is
    not there: either used to evaluate nothing, or something else, in silence."""
    shown = "saved steps: " + (", ".join(map(str, saved)) if len(saved) <= 8 else
                               f"{', '.join(map(str, saved[:4]))}, ..., "
                               f"{', '.join(map(str, saved[-2:]))} ({len(saved)} in all)")
    if every < 0:
        raise ValueError(f"every={every} is invalid; expected 0 (every checkpoint) or a step "
                         "interval >= 1, e.g. --every 2000")
    missing = sorted(set(steps or ()) - set(saved))
    if missing:
        raise ValueError(f"--steps {','.join(map(str, missing))}: {run} has no checkpoint "
                         f"there ({shown})")
    if every > 0 and not any(s % every == 0 and (steps is None or s in steps) for s in saved):
        raise ValueError(f"--every {every}: no checkpoint of {run} is at a multiple of "
                         f"{every}{' among --steps' if steps else ''} ({shown})")


def _evaluate_missing(run: Path, checkpoints: list[tuple[int, Path]], episodes: int,
                      every: int, n_envs: int, seed_start: int, steps: list[int] | None,
                      task: str, progress: bool, options: dict[str, Any]) -> None:
    variant = curve_variant(options)
    done = {r["step"] for r in read_curve(run, task, variant) if r.get("episodes") == episodes
            and r.get("seed_start") == seed_start}
    chosen = [(s, p) for s, p in checkpoints
              if (steps is None or s in steps) and (every <= 0 or s % every == 0)
              and s not in done]
    if chosen:
        from so101_sim.harness.warmup import warm_eval_workers

        # The first evaluation loads torch and its checkpoint here before it starts the env
        # workers: their fork server imports on the other core meanwhile, as eval's does.
        warm_eval_workers(videos=False)
    interrupts = Interrupts()  # SIGTERM too ends with the CLI's line, not a bare kill
    interrupts.install()
    try:
        for step, path in chosen:
            interrupts.check()  # a Ctrl-C lost in a garbage-collection callback stops it here
            _evaluate_step(run, task, step, path, episodes, n_envs, seed_start, progress,
                           options, variant)
    finally:
        interrupts.restore()


def _evaluate_step(run: Path, task: str, step: int, path: Path, episodes: int, n_envs: int,
                   seed_start: int, progress: bool, options: dict[str, Any],
                   variant: str) -> None:
    """One checkpoint's evaluation and its line in the curve file."""
    from so101_sim.harness.policies.factory import load_policy
    from so101_sim.harness.runner import evaluate

    info = read_train_info(path) or {}
    name = Path(task).stem  # a task given as a .toml path: its file name
    out = run / "eval_curve" / (f"{name}-{variant}" if variant else name) / f"step_{step:07d}"
    policy = load_policy(str(path), task=task, **options) if options else str(path)
    result = evaluate(policy, task=task, episodes=episodes, n_envs=n_envs,
                      seed_start=seed_start, out_dir=out, videos=0, resume=out.exists(),
                      progress=progress, report=False)
    agg = result["aggregated"]
    row = curve_row(task, step, round(agg["pc_success"] * episodes / 100), episodes,
                    seed_start, agg.get("failure_modes", {}),
                    train_hours=round(info.get("train_wall_s", 0) / 3600, 3),
                    variant=variant)
    append_line(run / CURVE_FILE, json.dumps(row))


def curve_row(task: str, step: int, successes: int, episodes: int, seed_start: int,
              failure_modes: dict[str, int], train_hours: float | None = None,
              variant: str = "") -> dict[str, Any]:
    """One checkpoint's line of ``eval_curve.jsonl``: its count with the Wilson interval."""
    lo, hi = wilson_interval(successes, episodes)
    return {"task": task, "step": step, "train_hours": train_hours, "episodes": episodes,
            "seed_start": seed_start, "successes": successes,
            "success": successes / episodes, "ci95": [round(lo, 4), round(hi, 4)],
            "failure_modes": failure_modes, **({"variant": variant} if variant else {})}


def widest_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per task and step: the one on the most seeds (a point first measured on 64
    seeds and later extended to 200 has both rows in the file)."""
    best: dict[tuple[str, int], dict[str, Any]] = {}
    for r in rows:
        key = (r.get("task", DEFAULT_TASK), r["step"])
        if key not in best or r["episodes"] > best[key]["episodes"]:
            best[key] = r
    return sorted(best.values(), key=lambda r: (r["step"], r.get("task", DEFAULT_TASK)))


def plot_curve(rows: list[dict[str, Any]], dest: Path, title: str = "",
               hours_key: str = "train_hours",
               hours_label: str = "trainer wall hours (incl. pauses)") -> Path:
    """Success (with 95% Wilson interval) against step and against training hours (the
    trainer's wall clock, or another hours column of the rows: `hours_key`); one line per task
    when the rows hold several (a multi-task run)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    tasks = sorted({r.get("task", DEFAULT_TASK) for r in rows})
    for ax, key, label in ((axes[0], "step", "training step"),
                           (axes[1], hours_key, hours_label)):
        for i, task in enumerate(tasks):
            mine = sorted((r for r in rows if r.get("task", DEFAULT_TASK) == task),
                          key=lambda r: r["step"])
            x = [r[key] for r in mine]
            color = f"C{i}" if len(tasks) > 1 else "tab:blue"
            ax.fill_between(x, [100 * r["ci95"][0] for r in mine],
                            [100 * r["ci95"][1] for r in mine], alpha=0.15 if len(tasks) > 1
                            else 0.25, color=color,
                            label=None if len(tasks) > 1 else "95% Wilson interval")
            ax.plot(x, [100 * r["success"] for r in mine], "o-", color=color,
                    label=task if len(tasks) > 1 else "success")
        ax.set_xlabel(label)
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success on evaluation seeds (%)")
    axes[0].legend(loc="upper left", fontsize=8)
    if rows:
        n = " or ".join(str(k) for k in sorted({r["episodes"] for r in rows}))
        fig.suptitle(title or f"closed-loop success, {n} seeds from {rows[-1]['seed_start']} "
                              "per checkpoint")
    fig.tight_layout()
    dest.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(dest, dpi=110)
    plt.close(fig)
    return dest
