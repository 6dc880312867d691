"""The output folder of an evaluation: per-episode records, the run's identity, the summary.

``episodes.jsonl`` gets one line per finished (or failed-to-run) episode, flushed as it ends,
so a killed run loses nothing and ``--resume`` runs only the missing seeds. ``eval_config.json``
records what was evaluated; resuming with a different policy, task, seed range or rendering
is refused. ``eval_info.json`` uses lerobot-eval's names (``per_episode``, ``aggregated`` with
``pc_success``, ``avg_sum_reward``, ``avg_max_reward``, ``eval_s``, ``eval_ep_s``) plus
the interval, failure modes and the time split.
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from so101_sim.harness.stats import wilson_interval

EPISODES = "episodes.jsonl"
CONFIG = "eval_config.json"
INFO = "eval_info.json"


@dataclass
class EpisodeRecord:
    """One line of episodes.jsonl. ``status`` is "ok" or "error" (the episode could not be
    run to its end, e.g. its worker died; it is run again and gets an "ok" line later)."""

    seed: int
    episode_ix: int
    status: str = "ok"
    success: bool = False
    failure_mode: str | None = None
    steps: int = 0
    sum_reward: float = 0.0
    max_reward: float = 0.0
    seconds: float = 0.0
    physics_s: float = 0.0
    render_s: float = 0.0
    policy_s: float = 0.0
    video: str | None = None
    actions_sha: str | None = None  # digest of the executed actions: equal = same rollout
    error: str | None = None

    @property
    def outcome(self) -> str:
        return "success" if self.success else (self.failure_mode or "failed")


class RunDir:
    """The files of one evaluation folder."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.episodes_path = self.path / EPISODES
        self.config_path = self.path / CONFIG
        self.info_path = self.path / INFO
        self.videos_dir = self.path / "videos"

    def prepare(self, identity: dict[str, Any], resume: bool) -> dict[int, EpisodeRecord]:
        """Create the folder, or check it for ``--resume``; return the episodes already done."""
        if self.episodes_path.exists() and not resume:
            raise ValueError(f"{self.path} already holds an evaluation ({EPISODES}); pass "
                             "--resume to finish it, or choose another --out")
        if resume and self.config_path.exists():
            try:
                old = json.loads(self.config_path.read_text(encoding="utf-8"))
                if not isinstance(old, dict):
                    raise ValueError("not a JSON object")
            except (ValueError, UnicodeDecodeError) as e:
                raise ValueError(f"cannot resume {self.path}: {self.config_path} is corrupt "
                                 f"({e}); delete that folder, or evaluate into a new --out"
                                 ) from None
            diff = [f"{k}: {old.get(k)!r} there, {v!r} now" for k, v in identity.items()
                    if old.get(k) != v]
            if diff:
                raise ValueError(f"cannot resume {self.path}: it holds a different evaluation ("
                                 + "; ".join(diff) + "); use the same arguments as that run, "
                                 "or a new --out")
        self.path.mkdir(parents=True, exist_ok=True)
        self.config_path.write_text(json.dumps(identity, indent=2) + "\n")
        if resume:
            self._drop_torn_tail()
        return self.done() if resume else {}

    def _drop_torn_tail(self) -> None:
        """Cut a last line that a kill left unfinished (no newline), so the next record
        starts on a line of its own instead of being glued to the fragment."""
        if not self.episodes_path.exists():
            return
        data = self.episodes_path.read_bytes()
        if data and not data.endswith(b"\n"):
            with self.episodes_path.open("r+b") as f:
                f.truncate(data.rfind(b"\n") + 1)

    def done(self) -> dict[int, EpisodeRecord]:
        """Finished episodes by seed (a torn last line from a killed run is skipped)."""
        out: dict[int, EpisodeRecord] = {}
        if not self.episodes_path.exists():
            return out
        for line in self.episodes_path.read_text().splitlines():
            try:
                rec = EpisodeRecord(**json.loads(line))
            except (json.JSONDecodeError, TypeError):
                continue
            if rec.status == "ok":
                out[rec.seed] = rec
        return out

    def append(self, rec: EpisodeRecord) -> None:
        with self.episodes_path.open("a") as f:
            f.write(json.dumps(asdict(rec)) + "\n")
            f.flush()

    def video_path(self, episode_ix: int, seed: int) -> Path:
        return self.videos_dir / f"episode_{episode_ix:04d}_seed{seed}.mp4"

    def write_info(self, info: dict[str, Any]) -> None:
        self.info_path.write_text(json.dumps(info, indent=2) + "\n")


def aggregate(records: list[EpisodeRecord], eval_s: float, n_run: int) -> dict[str, Any]:
    """lerobot-eval-style ``aggregated`` metrics over `records` (one per seed).

    ``eval_s`` is this invocation's wall time and ``eval_ep_s`` divides it by the episodes run
    in it (`n_run`), so a resumed run reports its own speed. ``time`` sums seconds over all
    episodes: physics and rendering in the workers (they overlap in wall time) and each
    episode's share of the batched policy calls.
    """
    n = len(records)
    k = sum(r.success for r in records)
    lo, hi = wilson_interval(k, n)
    modes = Counter(r.outcome for r in records if not r.success)
    mean = (lambda xs: sum(xs) / n) if n else (lambda xs: float("nan"))
    return {
        "pc_success": 100.0 * k / n if n else float("nan"),
        "success_ci95": [100.0 * lo, 100.0 * hi],
        "n_episodes": n,
        "n_success": k,
        "failure_modes": dict(sorted(modes.items())),
        "avg_sum_reward": mean([r.sum_reward for r in records]),
        "avg_max_reward": mean([r.max_reward for r in records]),
        "avg_episode_len": mean([r.steps for r in records]),
        "eval_s": eval_s,
        "eval_ep_s": eval_s / max(1, n_run),
        "time": {
            "physics_s": sum(r.physics_s for r in records),
            "render_s": sum(r.render_s for r in records),
            "policy_s": sum(r.policy_s for r in records),
            "episode_s_total": sum(r.seconds for r in records),
        },
    }


def per_episode(records: list[EpisodeRecord]) -> list[dict[str, Any]]:
    return [{"episode_ix": r.episode_ix, "seed": r.seed, "success": r.success,
             "failure_mode": r.failure_mode, "sum_reward": r.sum_reward,
             "max_reward": r.max_reward, "steps": r.steps, "seconds": r.seconds,
             "actions_sha": r.actions_sha,
             **({"video": r.video} if r.video else {})} for r in records]
