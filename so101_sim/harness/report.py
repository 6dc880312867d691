"""report.md and report.png for one evaluation folder: what was run, how well, how it failed."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from so101_sim.harness.results import EpisodeRecord
from so101_sim.utils.atomic import write_text_atomic
from so101_sim.utils.text import counted, md_row


def write_report(out_dir: str | Path, result: dict[str, Any],
                 records: Sequence[EpisodeRecord]) -> Path:
    """Write report.png (success with its interval, failure modes, episode lengths) and a
    report.md that shows it; return the markdown path."""
    out = Path(out_dir)
    agg, cfg = result["aggregated"], result["config"]
    _plot(out / "report.png", agg, records)
    lo, hi = agg["success_ci95"]
    t = agg["time"]
    lines = [
        f"# Evaluation: {cfg['policy']} on {cfg['task']}",
        "",
        f"**Success {agg['n_success']}/{agg['n_episodes']} = {agg['pc_success']:.1f}%** "
        f"(95% Wilson interval {lo:.1f}-{hi:.1f}%)",
        "",
        "![success, failure modes and episode lengths](report.png)",
        "",
        "| item | value |",
        "| --- | --- |",
        f"| seeds | {cfg['seed_start']}..{cfg['seed_start'] + cfg['episodes'] - 1} |",
        md_row("images", cfg["images"]),
        f"| failure modes | {_modes(agg['failure_modes'])} |",
        f"| avg episode length | {agg['avg_episode_len']:.1f} steps |",
        f"| avg sum / max reward | {agg['avg_sum_reward']:.3f} / {agg['avg_max_reward']:.3f} |",
        f"| wall time (this run) | {agg['eval_s']:.1f} s, {agg['eval_ep_s']:.2f} s/episode"
        f"{_envs_ran(cfg)} |",
        f"| physics / render / policy | {t['physics_s']:.1f} / {t['render_s']:.1f} / "
        f"{t['policy_s']:.1f} s (summed over episodes) |",
    ]
    lines += _worker_rows(cfg)
    for key, value in cfg.get("policy_details", {}).items():
        lines.append(md_row(key, value))
    lines.append(f"| policy fingerprint | `{cfg['policy_fingerprint']}` |")
    if cfg.get("software"):  # what else the numbers depend on
        soft = ", ".join(f"{k} {v}" for k, v in cfg["software"].items() if v)
        isa = f" (torch kernels: {cfg['cpu_isa']})" if cfg.get("cpu_isa") else ""
        lines.append(md_row("software / CPU", f"{soft} / {cfg.get('cpu', '?')}{isa}"))
    if cfg.get("video_paths"):
        lines += ["", "## Videos", ""]
        lines += [f"- [{Path(p).name}]({os.path.relpath(Path(p).resolve(), out.resolve())})"
                  for p in cfg["video_paths"]]
    path = out / "report.md"
    write_text_atomic(path, "\n".join(lines) + "\n")
    return path


def _worker_rows(cfg: dict[str, Any]) -> list[str]:
    """Where the envs ran, and every episode that had to be run again (and why)."""
    w = cfg.get("workers")
    rows = []
    if w and w.get("workers"):
        where = f"{w['backend']} backend, {counted(w['workers'], 'worker')} on "
        where += counted(w["nodes"], "node")
        if w.get("restarts"):
            where += f", {w['restarts']} replaced after dying"
        rows.append(f"| env workers | {where} |")
    for r in cfg.get("reruns", []):
        rows.append(md_row("re-run", f"seed {r['seed']}: {r['error']} (run again; the "
                                     "result counted is the re-run's)"))
    return rows


def _envs_ran(cfg: dict[str, Any]) -> str:
    """The envs that ran, not --n-envs: 2 episodes under the default 16 run on 2 workers."""
    ran = (cfg.get("workers") or {}).get("workers")
    return f", {counted(ran, 'env')}" if ran else ""


def _modes(modes: dict[str, int]) -> str:
    return ", ".join(f"{k}: {v}" for k, v in modes.items()) or "none"


def _plot(path: Path, agg: dict[str, Any], records: Sequence[EpisodeRecord]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(12, 3.6),
                                        gridspec_kw={"width_ratios": [1, 2, 2]})
    rate, (lo, hi) = agg["pc_success"], agg["success_ci95"]
    ax1.bar([0], [rate], color="tab:green", width=0.6)
    err = [[max(0.0, rate - lo)], [max(0.0, hi - rate)]]  # never negative, even by rounding
    ax1.errorbar([0], [rate], yerr=err, color="black", capsize=8)
    ax1.set(xlim=(-1, 1), ylim=(0, 100), xticks=[], ylabel="success (%)",
            title=f"{agg['n_success']}/{agg['n_episodes']}, 95% CI")

    modes = agg["failure_modes"] or {"(no failures)": 0}
    ax2.bar(list(modes), list(modes.values()), color="tab:red")
    ax2.set(ylabel="episodes", title="failure modes", ylim=(0, max(1, *modes.values()) * 1.1))
    ax2.yaxis.get_major_locator().set_params(integer=True)
    ax2.tick_params(axis="x", labelrotation=20)

    ok = [r.steps for r in records if r.success]
    bad = [r.steps for r in records if not r.success]
    ax3.hist([ok, bad], bins=20, stacked=True, color=["tab:green", "tab:red"],
             label=["success", "failure"])
    ax3.set(xlabel="episode length (steps)", ylabel="episodes", title="episode length")
    ax3.yaxis.get_major_locator().set_params(integer=True)
    ax3.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
