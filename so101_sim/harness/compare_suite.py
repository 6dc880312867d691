"""Two ``so101-sim eval --task a,b`` (or ``--task all``) folders compared task by task.

A suite folder holds one ordinary eval folder per task, so each shared task is compared as
``so101-sim compare`` compares two runs (same seeds, same task file, else refused), and the
pairs of all shared tasks are then pooled: every (task, seed) is an independent pair, so the
exact McNemar test and Newcombe's interval apply to the pooled counts unchanged. The pooled
difference weighs each task by its number of seeds, as the suite's "all" row does.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from shlex import quote
from typing import Any

from so101_sim.harness.compare import (
    JSON_NAME,
    MARKDOWN_NAME,
    compare_runs,
    load_run,
    same_folder_warning,
    suite_tasks,
    verdict,
    write_comparison,
)
from so101_sim.harness.stats import mcnemar_p_value, paired_difference_interval
from so101_sim.utils.atomic import write_json_atomic, write_text_atomic
from so101_sim.utils.text import counted

__all__ = ["compare_suites", "suite_summary_lines", "write_suite_comparison"]

COUNTS = ("both", "only_a", "only_b", "neither")


def compare_suites(run_a: str | Path, run_b: str | Path,
                   log: Callable[[str], None] = print) -> dict[str, Any]:
    """Each task both suites ran, compared seed by seed, and all of them pooled."""
    a, b = Path(run_a), Path(run_b)
    tasks_a, tasks_b = suite_tasks(a), suite_tasks(b)
    if tasks_a is None or tasks_b is None:
        load_run(b if tasks_a is not None else a)  # an unreadable other folder: its own error
        raise ValueError(mixed_error(a, b, tasks_a, tasks_b))
    shared = [t for t in tasks_a if t in tasks_b]
    if not shared:
        raise ValueError(f"{a} ({', '.join(tasks_a)}) and {b} ({', '.join(tasks_b)}) share no "
                         "task; evaluate both with the same --task list")
    only_a = [t for t in tasks_a if t not in tasks_b]
    only_b = [t for t in tasks_b if t not in tasks_a]
    if only_a or only_b:
        log(f"so101-sim compare: comparing the {counted(len(shared), 'task')} both ran; only "
            f"in A: {', '.join(only_a) or 'none'}, only in B: {', '.join(only_b) or 'none'}")
    same = a.resolve() == b.resolve()
    if same:
        log(same_folder_warning(a))
    per_task = {t: compare_runs(a / t, b / t, log=(lambda _: None) if same else log)
                for t in shared}
    counts = {k: sum(r["paired"][k] for r in per_task.values()) for k in COUNTS}
    n = sum(counts.values())
    lo, hi = paired_difference_interval(*(counts[k] for k in COUNTS))
    pooled = {"n_pairs": n, "paired": counts,
              "difference_pp": 100.0 * (counts["only_a"] - counts["only_b"]) / n,
              "difference_ci95_pp": [100.0 * lo, 100.0 * hi],
              "mcnemar_p_two_sided": mcnemar_p_value(counts["only_a"], counts["only_b"])}
    return {"a": str(a), "b": str(b), "tasks": shared, "tasks_only_a": only_a,
            "tasks_only_b": only_b, "per_task": per_task, "pooled": pooled}


def mixed_error(a: Path, b: Path, tasks_a: list[str] | None,
                tasks_b: list[str] | None) -> str:
    """A suite folder against a single task's: the command that pairs the matching task."""
    suite, other, tasks = (a, b, tasks_a) if tasks_a is not None else (b, a, tasks_b)
    task = load_run(other).task
    task = task if task in (tasks or []) else (tasks or ["TASK"])[0]
    pair = (suite / task, other) if suite == a else (other, suite / task)
    return (f"{suite} is an `so101-sim eval --task a,b` folder (one subfolder per task) and "
            f"{other} is one task's; compare that task's subfolder with it: "
            f"so101-sim compare {quote(str(pair[0]))} {quote(str(pair[1]))}")


def suite_summary_lines(r: dict[str, Any]) -> list[str]:
    """One row per shared task and one for all of them pooled (markdown)."""
    lines = [f"A: {r['a']}", f"B: {r['b']}",
             "| task | seeds | A | B | both | only A | only B | neither | A - B, points (95% CI) "
             "| McNemar p |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, x in [*r["per_task"].items(), ("all, pooled", r["pooled"])]:
        p = x["paired"]
        n = sum(p[k] for k in COUNTS)
        lo, hi = x["difference_ci95_pp"]
        lines.append(f"| {name} | {n} | {p['both'] + p['only_a']} | {p['both'] + p['only_b']} "
                     f"| {p['both']} | {p['only_a']} | {p['only_b']} | {p['neither']} | "
                     f"{x['difference_pp']:+.1f} ({lo:+.1f} to {hi:+.1f}) | "
                     f"{x['mcnemar_p_two_sided']:.4g} |")
    lines.append(f"pooled over {counted(len(r['tasks']), 'task')}: {verdict(r['pooled'])} "
                 "(exact McNemar on the discordant seeds of all tasks, two-sided)")
    return lines


def write_suite_comparison(r: dict[str, Any], out_dir: str | Path) -> tuple[Path, Path]:
    """compare.json and compare.md (the table) in `out_dir`, each task's own pair in
    `out_dir`/<task>/; returns the top two paths."""
    out = Path(out_dir)
    for task, result in r["per_task"].items():
        write_comparison(result, out / task)  # refuses an --out that is a file
    write_json_atomic(out / JSON_NAME, r)
    write_text_atomic(out / MARKDOWN_NAME,
                      "# Paired comparison, task by task\n\n"
                      + "\n".join(suite_summary_lines(r)) + "\n")
    return out / JSON_NAME, out / MARKDOWN_NAME
