"""Two evaluation folders on the same seeds, compared seed by seed: ``so101-sim compare A B``.

Episodes depend only on their seed, so two policies run on the same seeds form pairs, and the
seeds on which both succeed (or both fail) say nothing about which is better. The test is the
exact McNemar test on the discordant seeds; the difference A - B gets Newcombe's paired score
interval. Runs whose seeds or task differ are refused: their pairs would mean nothing.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from shlex import quote
from typing import Any

from so101_sim.harness.results import CONFIG, EPISODES, INFO, check_eval_info
from so101_sim.harness.stats import (
    mcnemar_p_value,
    paired_difference_interval,
    paired_split,
    wilson_interval,
)
from so101_sim.utils.atomic import write_json_atomic, write_text_atomic
from so101_sim.utils.text import counted, md_row
from so101_sim.utils.versions import SETUP_KEYS, setup_differences

JSON_NAME = "compare.json"
MARKDOWN_NAME = "compare.md"


@dataclass(frozen=True)
class RunSide:
    """What one evaluation folder says about itself and its episodes."""

    path: Path
    policy: str
    fingerprint: str
    task: str
    task_sha256: str | None
    images: str
    success: dict[int, bool]  # seed -> success
    actions_sha: dict[int, str | None]
    setup: dict[str, Any] = field(default_factory=dict)  # software versions, CPU (if recorded)
    render_size: tuple[int, int] | None = None  # the cameras' render size, if the policy saw them
    sequential: dict[str, Any] | None = None  # an `eval --against` run's sequential_verdict

    @property
    def n_success(self) -> int:
        return sum(self.success.values())

    def to_dict(self) -> dict[str, Any]:
        k, n = self.n_success, len(self.success)
        lo, hi = wilson_interval(k, n)
        return {"run": str(self.path), "policy": self.policy, "policy_fingerprint":
                self.fingerprint, "images": self.images, "n_success": k, "n_episodes": n,
                "pc_success": 100.0 * k / n, "success_ci95": [100.0 * lo, 100.0 * hi]}


def load_run(path: str | Path) -> RunSide:
    """Read ``eval_info.json`` of a finished ``so101-sim eval`` folder."""
    path = Path(path)
    info_path = path / INFO
    if not info_path.is_file():
        raise FileNotFoundError(f"{path} {missing_info_reason(path)}: expected the --out folder "
                                "of a finished `so101-sim eval`")
    try:
        info = json.loads(info_path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{info_path} is not JSON ({exc}); expected the eval_info.json that "
                         "`so101-sim eval` writes") from None
    tasks = tasks_of(info)
    if tasks is not None:
        raise ValueError(f"{path} is an `so101-sim eval --task a,b` folder, one subfolder per "
                         f"task: give one task's subfolder, e.g. {path / tasks[0]} "
                         "(only `so101-sim compare` takes two such folders whole)")
    if isinstance(info, dict) and "overall" in info and "per_episode" not in info:
        overall = info["overall"] if isinstance(info["overall"], dict) else {}
        raise ValueError(
            f"{info_path} is lerobot-eval's result ({overall.get('pc_success', '?')}% on "
            f"{overall.get('n_episodes', '?')} episodes), which keeps no seed per episode, so "
            "it cannot be paired seed by seed; evaluate the checkpoint with `so101-sim eval "
            "--policy CKPT --seed-start S --episodes N` (the seeds of the other run) instead")
    check_eval_info(info, info_path)  # a hand-edited "success": "no" is not a success
    try:
        cfg, episodes = info["config"], info["per_episode"]
        success = {int(e["seed"]): bool(e["success"]) for e in episodes}
        shas = {int(e["seed"]): e.get("actions_sha") for e in episodes}
        side = RunSide(path, str(cfg["policy"]), str(cfg.get("policy_fingerprint", "")),
                       str(cfg["task"]), cfg.get("task_sha256"), str(cfg.get("images", "?")),
                       success, shas, {k: cfg[k] for k in SETUP_KEYS if k in cfg},
                       seen_render_size(cfg), sequential_verdict(info))
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{info_path} is not an so101-sim eval result ({exc!r}); expected "
                         "the eval_info.json that `so101-sim eval` writes") from None
    if not success:
        raise ValueError(f"{info_path} holds no episodes; evaluate at least one")
    return side


def suite_tasks(path: str | Path) -> list[str] | None:
    """The tasks of an ``eval --task a,b`` folder, whose eval_info.json groups one subfolder
    per task (None for any other folder)."""
    try:
        info = json.loads((Path(path) / INFO).read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    return tasks_of(info)


def tasks_of(info: Any) -> list[str] | None:
    """The tasks of a parsed suite eval_info.json (None for any other content)."""
    if not isinstance(info, dict):
        return None
    config = info.get("config")
    tasks = config.get("tasks") if isinstance(config, dict) else None
    if "per_episode" in info or not isinstance(tasks, list) or not tasks \
            or not all(isinstance(t, str) and t for t in tasks):
        return None
    return tasks


def sequential_verdict(info: dict[str, Any]) -> dict[str, Any] | None:
    """The verdict an `eval --against` run stopped at (None for any other run)."""
    verdict = info.get("sequential_verdict")
    return verdict if isinstance(verdict, dict) and "verdict" in verdict else None


def seen_render_size(config: dict[str, Any]) -> tuple[int, int] | None:
    """The size a run rendered its policy's cameras at; None for a state-only policy, whose
    outcomes no render size touches (its render size is the videos')."""
    size = config.get("render_size")
    if not config.get("policy_image_size") or not isinstance(size, list | tuple):
        return None
    h, w = (int(x) for x in size)
    return h, w


def missing_info_reason(path: Path) -> str:
    """Why ``path`` holds no eval_info.json, in words that say what to do next."""
    if not path.exists():
        return "does not exist"
    if not path.is_dir():
        return "is a file, not a folder"
    if (path / EPISODES).is_file():
        return (f"has no {INFO} yet: its eval was interrupted; finish it by running its "
                f"command again with --out {quote(str(path))} --resume")
    runs = sorted(p.parent for p in path.glob(f"*/{EPISODES}"))
    if runs and all(_config_task(run) == run.name for run in runs):
        # `eval --task a,b` writes one folder per task, named after it, and the suite's file
        # after its last task
        return (f"has no {INFO} yet: it holds the tasks {', '.join(r.name for r in runs)} of "
                f"an interrupted `eval --task a,b`; finish it by running its command again "
                f"with --out {quote(str(path))} --resume")
    if runs:  # a folder of runs, as outputs/eval holds each default --out
        finished = [r for r in runs if (r / INFO).is_file()] or runs
        latest = max(finished, key=lambda r: (r / EPISODES).stat().st_mtime)
        shown = ", ".join(r.name for r in runs[:3]) + (
            f" and {len(runs) - 3} more" if len(runs) > 3 else "")
        return (f"has no {INFO}: it is a folder of {counted(len(runs), 'eval run')} ({shown}); "
                f"pass one of them, e.g. {latest}")
    return f"has no {INFO}"


def _config_task(run: Path) -> Any:
    """The task an eval folder's eval_config.json names (None if it has none to read)."""
    try:
        return json.loads((run / CONFIG).read_text(encoding="utf-8")).get("task")
    except (OSError, ValueError, AttributeError):
        return None


def check_comparable(a: RunSide, b: RunSide) -> None:
    """Refuse runs that are not pairs: another task (or task file), or other seeds."""
    problems = []
    if a.task != b.task:
        problems.append(f"task: A ran {a.task!r}, B ran {b.task!r}")
    elif a.task_sha256 and b.task_sha256 and a.task_sha256 != b.task_sha256:
        problems.append(f"task file: both ran {a.task!r}, but its settings differ (task_sha256 "
                        f"{a.task_sha256[:12]} vs {b.task_sha256[:12]}): it was edited between "
                        "the runs")
    other_seeds = set(a.success) != set(b.success)
    if other_seeds:
        only_a, only_b = sorted(set(a.success) - set(b.success)), sorted(set(b.success)
                                                                         - set(a.success))
        problems.append(f"seeds: A has {len(a.success)} ({seed_ranges(a.success)}), B has "
                        f"{len(b.success)} ({seed_ranges(b.success)})"
                        + (f"; only in A: {seed_ranges(only_a)}" if only_a else "")
                        + (f"; only in B: {seed_ranges(only_b)}" if only_b else ""))
    if problems:
        stopped = [f"{side} ({run.path}) is an `eval --against` run that stopped after "
                   f"{run.sequential.get('episodes', '?')} episodes with the verdict "
                   f"{run.sequential['verdict']!r}: that verdict, in its {INFO} "
                   "(sequential_verdict), is its comparison with "
                   f"{run.sequential.get('against', 'its reference')}; a fixed-size test on the "
                   "seeds where it stopped would not keep its error rate"
                   for side, run in (("A", a), ("B", b))
                   if run.sequential is not None and other_seeds]
        raise ValueError(f"cannot compare {a.path} (A) with {b.path} (B) seed by seed: "
                         + "; ".join(problems + stopped) + ". Evaluate both with the same "
                         "--task, --seed-start and --episodes" + _extend_hint(a, b))


def _extend_hint(a: RunSide, b: RunSide) -> str:
    """When one run's seeds are the first ones of the other's, `eval --resume` with more
    --episodes runs just the missing ones (the seeds already run are kept)."""
    if a.task != b.task:
        return ""
    for short, name, long in ((a, "A", b), (b, "B", a)):
        seeds, wanted = set(short.success), sorted(long.success)
        if (short.sequential is None and seeds and seeds < set(wanted)
                and min(seeds) == wanted[0] and wanted[-1] == wanted[0] + len(wanted) - 1):
            return (f"; to pair all {len(long.success)} seeds, extend {name}: run its eval "
                    f"command again with --out {quote(str(short.path))} --resume --episodes "
                    f"{len(long.success)} (the {len(short.success)} seeds already run are kept)")
    return ""


def compare_runs(run_a: str | Path, run_b: str | Path,
                 log: Callable[[str], None] = print) -> dict[str, Any]:
    """The paired comparison of two eval folders as a JSON-able dict (see module docstring).
    Comparing a folder with itself is allowed (a smoke test) but said, in one line, once the
    folder has been read: a missing or damaged one gets its error alone."""
    a, b = load_run(run_a), load_run(run_b)
    if Path(run_a).resolve() == Path(run_b).resolve():
        log(same_folder_warning(run_a))
    check_comparable(a, b)
    return paired_result(a, b)


def same_folder_warning(folder: str | Path) -> str:
    """The one line said when A and B are the same folder."""
    return (f"so101-sim compare: warning: A and B are the same folder ({folder}); every seed "
            "agrees with itself, so this says nothing about the policy: pass two eval folders")


def paired_result(a: RunSide, b: RunSide) -> dict[str, Any]:
    seeds = sorted(a.success)  # check_comparable: b has the same seeds
    both, only_a, only_b, neither_seeds = paired_split(a.success, b.success)
    n, neither = len(seeds), len(neither_seeds)
    lo, hi = paired_difference_interval(len(both), len(only_a), len(only_b), neither)
    same = sum(1 for s in seeds if a.actions_sha.get(s) and a.actions_sha[s] == b.actions_sha[s])
    return {
        "a": a.to_dict(), "b": b.to_dict(), "task": a.task, "n_seeds": n,
        "seeds": seed_ranges(seeds),
        "paired": {"both": len(both), "only_a": len(only_a), "only_b": len(only_b),
                   "neither": neither},
        "difference_pp": 100.0 * (len(only_a) - len(only_b)) / n,
        "difference_ci95_pp": [100.0 * lo, 100.0 * hi],
        "difference_interval": "Newcombe hybrid score interval for paired proportions "
                               "(Newcombe 1998, method 10), 95%",
        "mcnemar_p_two_sided": mcnemar_p_value(len(only_a), len(only_b)),
        "test": "exact McNemar (binomial on the discordant seeds), two-sided",
        "identical_rollouts": same,
        "seeds_only_a": only_a, "seeds_only_b": only_b,
        "setup_differences": setup_differences(a.setup, b.setup),
    }


def seed_ranges(seeds: Any, limit: int = 6) -> str:
    """Seeds as compact ranges: "100000..100049, 100060"; long lists end in "... (N ranges)"."""
    ordered = sorted(seeds)
    runs: list[tuple[int, int]] = []
    for s in ordered:
        if runs and s == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], s)
        else:
            runs.append((s, s))
    text = [f"{lo}..{hi}" if hi > lo else f"{lo}" for lo, hi in runs[:limit]]
    more = f", ... ({len(runs)} ranges)" if len(runs) > limit else ""
    return ", ".join(text) + more if text else "none"


def summary_lines(r: dict[str, Any]) -> list[str]:
    """The console summary: each run, the paired table, the difference and the test."""
    lines = []
    for key in ("a", "b"):
        s = r[key]
        lines.append(f"{key.upper()}: {s['policy']}: success {s['n_success']}/{s['n_episodes']}"
                     f" = {s['pc_success']:.1f}% (95% CI {s['success_ci95'][0]:.1f}-"
                     f"{s['success_ci95'][1]:.1f}); images: {s['images']} [{s['run']}]")
    p = r["paired"]
    lo, hi = r["difference_ci95_pp"]
    lines.append(f"paired on {counted(r['n_seeds'], 'seed')} of {r['task']} ({r['seeds']}): both "
                 f"succeed "
                 f"{p['both']}, only A {p['only_a']}, only B {p['only_b']}, neither "
                 f"{p['neither']}")
    lines.append(f"A - B = {r['difference_pp']:+.1f} points (95% CI {lo:+.1f} to {hi:+.1f}, "
                 f"Newcombe paired score); exact McNemar p = {r['mcnemar_p_two_sided']:.4g} "
                 f"(two-sided): {verdict(r)}")
    if r.get("setup_differences"):
        lines.append(setup_note(r["setup_differences"]))
    return lines


def setup_note(differences: list[str]) -> str:
    """One line: the runs did not share software or CPU, so some pairs may part for that."""
    return (f"note: the runs differ in {'; '.join(differences)}: actions then differ bitwise "
            "and some seeds' outcomes may differ for that reason alone, not the policy's")


def verdict(r: dict[str, Any], alpha: float = 0.05) -> str:
    if r["mcnemar_p_two_sided"] >= alpha:
        return f"no significant difference at {alpha:g}"
    better = "A" if r["difference_pp"] > 0 else "B"
    return f"{better} is significantly better at {alpha:g}"


def markdown(r: dict[str, Any]) -> str:
    p, a, b = r["paired"], r["a"], r["b"]
    lo, hi = r["difference_ci95_pp"]
    rows = [md_row(k.upper(), f"{s['policy']} (`{s['policy_fingerprint']}`)", s["images"],
                   f"{s['n_success']}/{s['n_episodes']} = {s['pc_success']:.1f}%",
                   f"{s['success_ci95'][0]:.1f}-{s['success_ci95'][1]:.1f}%", f"`{s['run']}`")
            for k, s in (("a", a), ("b", b))]
    lines = [
        f"# Paired comparison: {a['policy']} (A) vs {b['policy']} (B)", "",
        f"Task `{r['task']}`, the same {counted(r['n_seeds'], 'seed')} ({r['seeds']}).", "",
        "| run | policy | images | success | 95% Wilson | folder |",
        "| --- | --- | --- | --- | --- | --- |", *rows, "",
        "## Seed by seed", "",
        "| | B succeeded | B failed |", "| --- | --- | --- |",
        f"| **A succeeded** | {p['both']} | {p['only_a']} |",
        f"| **A failed** | {p['only_b']} | {p['neither']} |", "",
        f"- **A - B = {r['difference_pp']:+.1f} points**, 95% interval {lo:+.1f} to {hi:+.1f} "
        f"({r['difference_interval']})",
        f"- exact McNemar test on the {p['only_a'] + p['only_b']} discordant seeds: "
        f"p = {r['mcnemar_p_two_sided']:.4g} (two-sided): {verdict(r)}",
        f"- identical rollouts (same executed actions): {r['identical_rollouts']} seeds",
        f"- seeds only A solved: {_seed_list(r['seeds_only_a'])}",
        f"- seeds only B solved: {_seed_list(r['seeds_only_b'])}",
        *([f"- {setup_note(r['setup_differences'])}"] if r.get("setup_differences") else []),
    ]
    return "\n".join(lines) + "\n"


def _seed_list(seeds: list[int], limit: int = 30) -> str:
    if not seeds:
        return "none"
    return ", ".join(map(str, seeds[:limit])) + (f", ... ({len(seeds)})" if len(seeds) > limit
                                                  else "")


def write_comparison(r: dict[str, Any], out_dir: str | Path) -> tuple[Path, Path]:
    """compare.json and compare.md in `out_dir`; returns their paths."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"compare --out {out} is a file; expected a folder for {JSON_NAME} "
                         f"and {MARKDOWN_NAME}: choose another --out (or leave it out)")
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / JSON_NAME, r)
    write_text_atomic(out / MARKDOWN_NAME, markdown(r))
    return out / JSON_NAME, out / MARKDOWN_NAME
