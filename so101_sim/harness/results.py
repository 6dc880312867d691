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
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from so101_sim.harness.stats import wilson_interval
from so101_sim.utils.atomic import append_line, drop_torn_tail, read_jsonl, write_json_atomic
from so101_sim.utils.locks import hold_folder
from so101_sim.utils.paths import foreign_folder
from so101_sim.utils.versions import setup_differences

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
        self.setups: list[dict[str, Any]] = []  # those its episodes ran with (``prepare``)

    def check_target(self, resume: bool) -> None:
        """Refuse a folder an eval must not write into; it needs no policy, so ``eval`` asks
        before it loads one."""
        if (what := foreign_folder(self.path)) is not None:  # e.g. --out the --policy folder
            raise ValueError(f"{self.path} {what}; an eval writes {INFO}, report.md and "
                             "videos/ there, over or among its files; choose another --out")
        if self.episodes_path.exists() and not resume:
            raise ValueError(f"{self.path} already holds an evaluation ({EPISODES}); pass "
                             "--resume to finish it, or choose another --out")

    def prepare(self, identity: dict[str, Any], resume: bool, may_grow: tuple[str, ...] = (),
                setup: dict[str, Any] | None = None) -> dict[int, EpisodeRecord]:
        """Create the folder, or check it for ``--resume``; return the episodes already done.
        A count named in `may_grow` (``episodes``: the seeds run in order, so a longer run
        starts with the shorter one's seeds) may be larger than the folder's on resume.
        `setup` (``utils.versions.run_setup``) joins the setups its episodes ran with."""
        old: dict[str, Any] = {}
        self.check_target(resume)
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
                    if old.get(k) != v and not _grows(k, old.get(k), v, may_grow)]
            if len(diff) == 1 and diff[0].startswith("policy_fingerprint:"):
                diff[0] += f" ({SAME_NAME_OTHER_POLICY})"
            if diff:
                raise ValueError(f"cannot resume {self.path}: it holds a different evaluation ("
                                 + "; ".join(diff) + "); use the same arguments as that run, "
                                 "or a new --out")
        self.path.mkdir(parents=True, exist_ok=True)
        if resume:
            drop_torn_tail(self.episodes_path)  # the next record starts on a line of its own
        done = self.done() if resume else {}
        if setup is not None:  # the setups that differ from this one, then this one
            earlier = old.get("setups") if done and isinstance(old.get("setups"), list) else []
            self.setups = [s for s in earlier if isinstance(s, dict)
                           and setup_differences(s, setup)] + [setup]
        write_json_atomic(self.config_path, {**identity, "setups": self.setups})
        return done

    def earlier_setups(self) -> dict[str, Any]:
        """For eval_info's config: the other setups this folder's episodes ran with, if any."""
        return {"earlier_setups": self.setups[:-1]} if len(self.setups) > 1 else {}

    def setup_note(self) -> str:
        """One line when episodes in this folder ran with another setup than this run's."""
        if len(self.setups) < 2:
            return ""
        differ = "; ".join(setup_differences(self.setups[0], self.setups[-1]))
        return (f"so101-sim eval: note: the episodes already in {self.path} ran with another "
                f"setup ({differ}, then vs now); actions differ bitwise between setups, so this "
                "run's results mix them")

    def save_video(self, path: str | None, mp4: bytes | None) -> str | None:
        """Write a worker's episode video under its final name (whole, or not at all)."""
        if path is None or mp4 is None:
            return None
        final = Path(path)
        final.parent.mkdir(parents=True, exist_ok=True)
        part = final.with_name(final.stem + ".part.mp4")
        part.write_bytes(mp4)
        part.replace(final)
        return str(final)

    def done(self) -> dict[int, EpisodeRecord]:
        """Finished episodes by seed (a torn last line from a killed run is dropped; a line
        with a wrong key or value is refused, naming the file, line and key)."""
        out: dict[int, EpisodeRecord] = {}
        try:
            rows = read_jsonl(self.episodes_path)
        except ValueError as exc:
            raise ValueError(f"{exc} (its episode runs again on --resume)") from None
        for n, row in enumerate(rows, 1):
            rec = check_record(row, f"{self.episodes_path} line {n}")
            if rec.status == "ok":
                out[rec.seed] = rec
        return out

    def append(self, rec: EpisodeRecord) -> None:
        """One line per episode, synced: a kill keeps it whole or only cuts this line."""
        append_line(self.episodes_path, json.dumps(asdict(rec)))

    def video_path(self, episode_ix: int, seed: int) -> Path:
        return self.videos_dir / f"episode_{episode_ix:04d}_seed{seed}.mp4"

    def write_info(self, info: dict[str, Any]) -> None:
        write_json_atomic(self.info_path, info)


SAME_NAME_OTHER_POLICY = ("the same checkpoint name with other weights, or other inference "
                          "flags: --n-action-steps, --inference-steps, --noise-scheduler, "
                          "--temporal-ensemble, --precision, --policy-batch, --camera-map")
"""What a fingerprint alone differing means: it hashes the weights and these settings."""


def _grows(key: str, old: Any, new: Any, may_grow: tuple[str, ...]) -> bool:
    return key in may_grow and isinstance(old, int) and isinstance(new, int) and new > old


def lock_eval_folders(out: Path, save_rollouts: str | Path | None) -> None:
    """Hold the evaluation folder (and the rollout dataset's) for the rest of the
    ``@lock_scope`` call: a second run into either is refused before it writes anything. A
    run that fails before its first episode leaves no folder it created behind."""
    hold_folder(out, "the evaluation", stub=(CONFIG,))
    if save_rollouts is not None:
        hold_folder(Path(save_rollouts).expanduser(), "the rollout dataset")


_NUMBERS = ("sum_reward", "max_reward", "seconds", "physics_s", "render_s", "policy_s")
_TEXTS = ("failure_mode", "video", "actions_sha", "error")


def value_problem(key: str, value: Any) -> str | None:
    """What an episode's `key` should hold, if `value` does not (None when it is fine)."""
    is_int = isinstance(value, int) and not isinstance(value, bool)
    if key == "seed":
        return None if is_int and 0 <= value < 2**32 else "an integer seed 0..2**32-1"
    if key in ("episode_ix", "steps"):
        return None if is_int and value >= 0 else "an integer >= 0"
    if key == "status":
        return None if value in ("ok", "error") else '"ok" or "error"'
    if key == "success":
        return None if isinstance(value, bool) else "true or false (JSON booleans)"
    if key in _NUMBERS:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        return None if ok else "a number"
    if key in _TEXTS:
        return None if value is None or isinstance(value, str) else "a string or null"
    return None


def check_record(row: Any, where: str) -> EpisodeRecord:
    """An episodes.jsonl line as a record, or ValueError naming `where`, the key and what it
    should hold (a hand-edited ``"success": "no"`` must not count as a success)."""
    if not isinstance(row, dict):
        raise ValueError(f"{where} is {type(row).__name__}; expected a JSON object (one "
                         "episode); fix or delete that line")
    known = {f.name for f in fields(EpisodeRecord)}
    unknown = sorted(set(row) - known)
    missing = [k for k in ("seed", "episode_ix") if k not in row]
    if unknown or missing:
        raise ValueError(f"{where}: {'unknown keys ' + str(unknown) if unknown else ''}"
                         f"{'; ' if unknown and missing else ''}"
                         f"{'missing ' + str(missing) if missing else ''}; expected the keys "
                         f"{sorted(known)}; fix or delete that line")
    for key, value in row.items():
        want = value_problem(key, value)
        if want:
            raise ValueError(f"{where}: {key} = {value!r} is invalid; expected {want}; fix "
                             "or delete that line (its episode runs again on --resume)")
    return EpisodeRecord(**row)


def check_eval_info(info: Any, path: Path) -> None:
    """Refuse an ``eval_info.json`` whose values a reader would misread: types, seeds outside
    the run's range or twice, counts that disagree with its episodes (or its episodes.jsonl).
    The message names the file and the key; ``eval --resume`` with the run's arguments
    writes the file again from episodes.jsonl."""
    fix = ("it was edited or is not from so101-sim eval; rerun the evaluation with its "
           "arguments plus --resume to rewrite it from episodes.jsonl")

    def bad(key: str, value: Any, want: str) -> ValueError:
        return ValueError(f"{path}: {key} = {value!r} is invalid; expected {want}; {fix}")

    if not isinstance(info, dict):
        raise bad("(top level)", type(info).__name__, "a JSON object")
    for key, typ in (("config", dict), ("per_episode", list), ("aggregated", dict)):
        value = info.get(key, {} if key == "aggregated" else None)  # aggregated: optional
        if not isinstance(value, typ):
            raise bad(key, value, f"a JSON {'object' if typ is dict else 'list'}")
    cfg, agg = info["config"], info.get("aggregated", {})
    start, n = cfg.get("seed_start"), cfg.get("episodes")
    seen: dict[int, bool] = {}
    for i, e in enumerate(info["per_episode"]):
        if not isinstance(e, dict):
            raise bad(f"per_episode[{i}]", e, "a JSON object")
        for key in ("seed", "success", "steps", "failure_mode", "actions_sha"):
            want = value_problem(key, e.get(key)) if key in e or key in ("seed", "success") \
                else None
            if want:
                raise bad(f"per_episode[{i}].{key}", e.get(key), want)
        seed = e["seed"]
        if isinstance(start, int) and isinstance(n, int) and not start <= seed < start + n:
            raise bad(f"per_episode[{i}].seed", seed, f"a seed in {start}..{start + n - 1} "
                      "(config.seed_start, config.episodes)")
        if seed in seen:
            raise bad(f"per_episode[{i}].seed", seed, "each seed once")
        seen[seed] = e["success"]
    for key, count in (("n_episodes", len(seen)), ("n_success", sum(seen.values()))):
        if key in agg and agg[key] != count:
            raise bad(f"aggregated.{key}", agg[key], f"{count}, as per_episode has it")
    log = path.parent / EPISODES
    if log.is_file():
        logged = RunDir(path.parent).done()
        for seed, success in seen.items():
            if seed in logged and logged[seed].success != success:
                raise ValueError(f"{path}: per_episode seed {seed} has success = {success}, "
                                 f"but {log} has {logged[seed].success}; {fix}")


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


def summary_line(policy: str, task: str, agg: dict[str, Any], out: Path,
                 images: str | None = None) -> str:
    lo, hi = agg["success_ci95"]
    t = agg["time"]
    modes = ", ".join(f"{k} {v}" for k, v in agg["failure_modes"].items()) or "none"
    return (f"{policy} on {task}: success {agg['n_success']}/{agg['n_episodes']} = "
            f"{agg['pc_success']:.1f}% (95% CI {lo:.1f}-{hi:.1f}); failures: {modes}; "
            f"avg length {agg['avg_episode_len']:.0f} steps; {agg['eval_s']:.1f} s "
            f"({agg['eval_ep_s']:.2f} s/episode; physics {t['physics_s']:.1f} s, render "
            f"{t['render_s']:.1f} s, policy {t['policy_s']:.1f} s)"
            + (f"; images: {images}" if images else "") + f" -> {out}")
