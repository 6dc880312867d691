"""Success of a policy on the sim robot driven by lerobot's own tools, per seed, to pair with
``so101-sim eval`` on the same seeds.

    so101-sim eval --policy policy/pick_place_diffusion --episodes 30 --seed-start 100000 \\
        --faithful --out outputs/eval/agreement
    python plugins/lerobot_robot_so101_sim/agreement.py rollout --episodes 30 \\
        --seed-start 100000 --pair outputs/eval/agreement

``rollout`` runs ``lerobot-rollout --strategy.type=episodic`` (sync inference) on seeds
S..S+N-1: one dataset episode per seed, the policy reset at each, frames rendered at the
checkpoint's recorded size and resized with so101-sim's training resize, as ``so101-sim eval
--faithful`` does (``--render-size HxW``: as its ``--image-size HxW``). A lerobot episode lasts
``--episode-time-s`` of wall time whatever happens in it (the scene holds after the sim's end),
so an episode still running then is reported as unfinished: raise the time. ``async`` runs
lerobot's policy server (a subprocess on a loopback port) and its ``RobotClient`` (in this
process, unchanged, timing each action chunk from the observation's capture to its arrival);
the sim starts the next seed as soon as an episode ends and the client has no notion of
episodes, so the first chunk of an episode may still come from the previous one's frames
(lerobot's own log files go to ``<out>/logs``). Per-seed lines, the rate with its Wilson
interval and a JSON summary (``<out>/agreement.json``) come out; ``--pair DIR`` adds ``so101-sim
compare``'s paired table (lerobot as A) against a finished ``so101-sim eval`` folder of the same
task, read and checked before lerobot starts.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from shlex import quote
from typing import Any

from so101_sim.cli.arg_types import (
    nonnegative_int,
    parse_image_size,
    positive_float,
    positive_int,
    unit_fraction,
)
from so101_sim.utils.locks import file_in_the_way

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
LEROBOT_ISSUE = "https://github.com/huggingface/lerobot/issues/3861"


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    task = _task(args.task)
    # used only at the end, read now: a wrong folder found then cost the whole run
    pair = _pair_run(Path(args.pair), task, args) if args.pair else None
    out = Path(args.out or f"outputs/agreement/{args.mode}")
    if (blocking := file_in_the_way(out)) is not None:  # mkdir raised FileExistsError or
        # NotADirectoryError
        raise SystemExit(f"--out {out}: {blocking} is a file; expected a folder for the "
                         "outcomes, logs and agreement.json: choose another --out")
    policy = _policy_info(Path(args.policy))
    outcomes_path = out / "outcomes.jsonl"
    robot = _robot_flags(args, policy, outcomes_path)
    if args.mode == "async":
        _check_async(args, policy)
    out.mkdir(parents=True, exist_ok=True)
    outcomes_path.unlink(missing_ok=True)
    latency: list[float] = []
    if args.mode == "rollout":
        _run_rollout(args, policy, task, out, robot)
    else:
        latency = _run_async(args, policy, task, out, robot)
    return _report(args, out, outcomes_path, latency, pair)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mode", choices=["rollout", "async"],
                   help="rollout: lerobot-rollout episodic; async: policy server + robot client")
    p.add_argument("--policy", default=str(REPO / "policy" / "pick_place_diffusion"),
                   help="checkpoint folder (default: the shipped policy)")
    p.add_argument("--task", default="pick_place", help="suite task name or task TOML path")
    p.add_argument("--episodes", type=positive_int, default=30, help="seeds to run (N)")
    p.add_argument("--seed-start", type=nonnegative_int, default=100_000, help="first seed (S)")
    p.add_argument("--out", default=None, help="folder for outcomes, logs, the rollout dataset")
    p.add_argument("--render-size", type=parse_image_size, default=None, metavar="HxW",
                   help="render size, as `so101-sim eval --image-size` renders it (default: "
                        "the checkpoint's recorded size, so101_sim_train.json "
                        "dataset_image_size, else its input size: eval's --faithful)")
    p.add_argument("--episode-time-s", type=positive_float, default=None,
                   help="rollout: wall seconds per lerobot episode (default: 4x the task's "
                        "episode length at its fps)")
    p.add_argument("--realtime", action="store_true",
                   help="rollout: pace the sim at the task's fps (default: as fast as it runs)")
    p.add_argument("--pair", default=None, metavar="EVAL_DIR",
                   help="so101-sim eval folder of the same seeds: print the paired table")
    p.add_argument("--port", type=nonnegative_int, default=0,
                   help="async: server port (0: a free one)")
    p.add_argument("--actions-per-chunk", type=positive_int, default=None,
                   help="async: actions per chunk (default: the policy's n_action_steps)")
    p.add_argument("--chunk-size-threshold", type=unit_fraction, default=0.5,
                   help="async: the client sends an observation for a new chunk once its "
                        "queue holds at most this fraction of a chunk (lerobot's "
                        "chunk_size_threshold)")
    p.add_argument("--aggregate-fn", default="weighted_average",
                   help="async: how overlapping chunks are merged (lerobot's "
                        "aggregate_fn_name)")
    p.add_argument("--patch-diffusion", action="store_true",
                   help="async: serve with lerobot_robot_so101_sim.patched_server, lerobot "
                        "0.6.1's policy server made to run a Diffusion Policy with n_obs_steps "
                        f"> 1 (it fails otherwise, {LEROBOT_ISSUE}): a single observation is "
                        "repeated over the history, as select_action does at an episode's "
                        "first step")
    return p


# --------------------------------------------------------------------------- the policy
def _policy_info(path: Path) -> dict[str, Any]:
    """Type, cameras, input size, recorded size and chunk length of a checkpoint folder."""
    for name in ("config.json", "model.safetensors"):  # lerobot failed on it after starting
        if not (path / name).is_file():
            raise SystemExit(f"--policy {path}: no {name} there; expected a checkpoint folder "
                             "(pretrained_model), e.g. policy/pick_place_diffusion")
    cfg_path = path / "config.json"
    cfg = json.loads(cfg_path.read_text())
    cams, size = [], None
    for key, feat in cfg.get("input_features", {}).items():
        if feat.get("type") == "VISUAL":
            cams.append(key.rsplit(".", 1)[-1])
            size = tuple(feat["shape"][1:])
    recorded = None
    train_json = path / "so101_sim_train.json"
    if train_json.is_file():
        recorded = json.loads(train_json.read_text()).get("dataset_image_size")
    return {"path": path, "type": cfg["type"], "cameras": cams, "image_size": size,
            "recorded_size": tuple(recorded) if recorded else None,
            "n_obs_steps": int(cfg.get("n_obs_steps", 1)),
            "n_action_steps": int(cfg.get("n_action_steps", cfg.get("chunk_size", 1)))}


def _robot_flags(args: argparse.Namespace, policy: dict[str, Any],
                 outcomes_path: Path) -> dict[str, Any]:
    """SO101SimConfig fields that render the policy's frames as ``so101-sim eval`` does: its
    faithful path, or with --render-size, its --image-size of that size (the same mesh detail)."""
    from so101_sim.harness.frames import choose_rendering
    from so101_sim.harness.policies import PolicyInfo

    if policy["image_size"] is None:
        raise SystemExit(f"--policy {policy['path']}: no camera input; this script measures "
                         "image policies")
    try:
        info = PolicyInfo(name=str(policy["path"]), cameras=tuple(policy["cameras"]),
                          image_size=policy["image_size"],
                          train_image_size=policy["recorded_size"])
    except ValueError as exc:  # a camera the sim lacks
        raise SystemExit(f"--policy {policy['path']}: {exc}") from None
    rendering = choose_rendering(info, args.render_size, faithful=args.render_size is None)
    (h, w), (rh, rw) = policy["image_size"], rendering.render_size
    return {"task": args.task, "seed": args.seed_start, "camera_names": policy["cameras"],
            "image_height": h, "image_width": w, "render_height": rh, "render_width": rw,
            "mesh_width": rendering.mesh_width or 0, "outcomes_path": outcomes_path}


def _task(name: str) -> Any:
    """The suite task or task TOML, refused in one line (a traceback once --out was made)."""
    from so101_sim.tasks import load_task

    try:
        return load_task(name)
    except ValueError as exc:
        raise SystemExit(f"--task {name!r} is invalid: {exc}") from None


# --------------------------------------------------------------------------- rollout
def _run_rollout(args: argparse.Namespace, policy: dict[str, Any], task: Any, out: Path,
                 robot: dict[str, Any]) -> None:
    episode_s = args.episode_time_s or 4 * task.max_steps / task.fps
    robot = {**robot, "realtime": args.realtime}
    flags = [f"--robot.{k}={_flag_value(v)}" for k, v in robot.items()]
    dataset = out / "rollout_dataset"
    if dataset.exists():
        import shutil

        shutil.rmtree(dataset)
    cmd = [str(BIN / "lerobot-rollout"), "--strategy.type=episodic",
           f"--policy.path={policy['path']}", "--robot.type=so101_sim", *flags,
           "--dataset.repo_id=local/rollout_so101_sim_agreement", f"--dataset.root={dataset}",
           f"--dataset.num_episodes={args.episodes}", f"--dataset.episode_time_s={episode_s}",
           "--dataset.reset_time_s=0", "--dataset.push_to_hub=false", "--dataset.no_stamp=true",
           "--dataset.rgb_encoder.vcodec=h264", f"--dataset.single_task={task.description}",
           "--strategy.reset_to_initial_position=false", "--return_to_initial_position=false",
           f"--fps={task.fps}", "--play_sounds=false"]
    print(f"agreement: {args.episodes} episodes of lerobot-rollout episodic, "
          f"{episode_s:.0f} s each; log in {out / 'rollout.log'}", flush=True)
    _run_logged(cmd, out / "rollout.log")


def _flag_value(v: Any) -> str:
    if isinstance(v, list):
        return "[" + ",".join(v) + "]"
    return str(v).lower() if isinstance(v, bool) else str(v)


def _run_logged(cmd: list[str], log: Path) -> None:
    env = {**os.environ, "HF_HUB_OFFLINE": os.environ.get("HF_HUB_OFFLINE", "1")}
    with open(log, "w", encoding="utf-8") as f:
        run = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                             env=env, check=False)
    if run.returncode != 0:
        from lerobot_robot_so101_sim.async_run import log_tail  # the package imports lerobot

        raise SystemExit(f"{Path(cmd[0]).name} exited with {run.returncode}; the end of "
                         f"{log}:\n{log_tail(log)}")


# --------------------------------------------------------------------------- async
def _run_async(args: argparse.Namespace, policy: dict[str, Any], task: Any, out: Path,
               robot: dict[str, Any]) -> list[float]:
    """Policy server in a subprocess, RobotClient here; returns chunk latencies (s)."""
    from lerobot_robot_so101_sim.async_run import AsyncRun, run_async  # imports grpc

    run = AsyncRun(policy_path=policy["path"], policy_type=policy["type"], task=task,
                   episodes=args.episodes,
                   actions_per_chunk=args.actions_per_chunk or policy["n_action_steps"],
                   chunk_size_threshold=args.chunk_size_threshold,
                   aggregate_fn=args.aggregate_fn, port=args.port,
                   patch_diffusion=args.patch_diffusion)
    return run_async(run, out, robot)


def _check_async(args: argparse.Namespace, policy: dict[str, Any]) -> None:
    from lerobot.async_inference.configs import AGGREGATE_FUNCTIONS

    if args.aggregate_fn not in AGGREGATE_FUNCTIONS:  # lerobot's client raised after the
        # policy server had started
        raise SystemExit(f"--aggregate-fn {args.aggregate_fn!r} is not one of lerobot's: "
                         f"expected one of {', '.join(AGGREGATE_FUNCTIONS)}")
    if policy["type"] == "diffusion" and policy["n_obs_steps"] > 1 and not args.patch_diffusion:
        raise SystemExit(f"--policy {policy['path']} is a Diffusion Policy with n_obs_steps="
                         f"{policy['n_obs_steps']}: lerobot 0.6.1's policy server fails on it "
                         "(AssertionError in generate_actions: it passes one observation to "
                         f"predict_action_chunk; {LEROBOT_ISSUE}); pass --patch-diffusion to "
                         "run it with a single observation repeated over the history")


# --------------------------------------------------------------------------- report
def _report(args: argparse.Namespace, out: Path, outcomes_path: Path,
            latency: list[float], pair: Any) -> int:
    from so101_sim.harness.stats import wilson_interval

    rows = [json.loads(line) for line in outcomes_path.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if not r["discarded"] and r["ended_by"] != "disconnect"]
    by_seed = {r["seed"]: r for r in rows}
    seeds = _seeds(args)
    missing = [s for s in seeds if s not in by_seed]
    for s in seeds:
        r = by_seed.get(s)
        if r is None:
            print(f"seed {s}: not run")
            continue
        what = "success" if r["success"] else r["failure_mode"]
        print(f"seed {s}: {what} ({r['steps']} steps)")
    done = [by_seed[s] for s in seeds if s in by_seed]
    unfinished = [r["seed"] for r in done if r["failure_mode"] == "unfinished"]
    k, n = sum(r["success"] for r in done), len(done)
    summary: dict[str, Any] = {"mode": args.mode, "policy": str(args.policy), "task": args.task,
                               "seed_start": args.seed_start, "episodes": n, "successes": k,
                               "unfinished": unfinished, "missing": missing,
                               "per_seed": {str(r["seed"]): r["success"] for r in done}}
    if n:
        lo, hi = wilson_interval(k, n)
        summary["rate"], summary["wilson95"] = k / n, [lo, hi]
        print(f"success: {k}/{n} = {100 * k / n:.1f}% (95% Wilson {100 * lo:.1f}-"
              f"{100 * hi:.1f})")
    if len(latency) > 1:  # the first chunk waits for the server's warm-up: apart
        ms = sorted(1000 * v for v in latency[1:])
        summary["latency_ms"] = {"chunks": len(ms), "median": ms[len(ms) // 2],
                                 "p90": ms[min(len(ms) - 1, int(0.9 * len(ms)))],
                                 "max": ms[-1], "first_chunk": 1000 * latency[0]}
        lat = summary["latency_ms"]
        print(f"action latency (observation captured -> its chunk received): median "
              f"{lat['median']:.0f} ms, p90 {lat['p90']:.0f} ms, max {lat['max']:.0f} ms over "
              f"{lat['chunks']} chunks (the first, with the server's warm-up: "
              f"{lat['first_chunk']:.0f} ms)")
    print(f"pair with: {_eval_command(args)}")
    if pair is not None:
        summary["paired"] = _paired(args, out, pair, {r["seed"]: r["success"] for r in done
                                                      if r["seed"] not in unfinished})
    (out / "agreement.json").write_text(json.dumps(summary, indent=2) + "\n")
    if unfinished:
        print(f"agreement: {len(unfinished)} episodes were still running when lerobot's episode "
              "ended; raise --episode-time-s", file=sys.stderr)
    return 1 if unfinished or missing else 0


def _seeds(args: argparse.Namespace) -> range:
    """The seeds this run covers: S..S+N-1."""
    return range(args.seed_start, args.seed_start + args.episodes)


def _size_flag(args: argparse.Namespace) -> str:
    """The eval flag that renders the frames this run renders (_robot_flags)."""
    return (f"--image-size {args.render_size[0]}x{args.render_size[1]}" if args.render_size
            else "--faithful")


def _eval_command(args: argparse.Namespace) -> str:
    return (f"so101-sim eval --policy {quote(str(args.policy))} --task {args.task} --episodes "
            f"{args.episodes} --seed-start {args.seed_start} {_size_flag(args)}")


def _pair_run(eval_dir: Path, task: Any, args: argparse.Namespace) -> Any:
    """The eval folder to pair with, read as `so101-sim compare` reads one (a finished eval,
    checked) and refused unless it ran this task (the same task file) on some of these seeds."""
    from so101_sim.harness.compare import load_run, seed_ranges

    try:
        run = load_run(eval_dir)
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f"--pair: {exc}") from None
    fix = f"pair with the folder of `{_eval_command(args)} --out DIR`"
    if run.task != task.name or (run.task_sha256 and run.task_sha256 != task.sha256()):
        other = ("" if run.task != task.name else " with other settings (its task_sha256 "
                 f"{run.task_sha256[:12]}, this one {task.sha256()[:12]})")
        raise SystemExit(f"--pair {eval_dir} is an eval of task {run.task!r}{other}; this run "
                         f"is --task {args.task!r}: {fix}")
    seeds = _seeds(args)
    missing = [s for s in seeds if s not in run.success]
    if len(missing) == len(seeds):
        raise SystemExit(f"--pair {eval_dir} holds seeds {seed_ranges(run.success)}, none of "
                         f"this run's {seed_ranges(seeds)}: {fix}")
    if missing:
        print(f"agreement: --pair {eval_dir} lacks {len(missing)} of the {len(seeds)} seeds "
              f"({seed_ranges(missing)}); the paired table leaves them out", flush=True)
    return run


def _paired(args: argparse.Namespace, out: Path, run: Any, ours: dict[int, bool]
            ) -> dict[str, Any] | None:
    """`so101-sim compare`'s paired result and lines, lerobot's outcomes as A and the eval
    folder's as B, on the seeds both ran."""
    from dataclasses import replace

    from so101_sim.harness.compare import RunSide, paired_result, summary_lines
    from so101_sim.utils.versions import run_setup

    shared = sorted(s for s in ours if s in run.success)
    if not shared:
        print(f"agreement: no seed of {args.pair} finished here; nothing to pair")
        return None
    tool = "lerobot-rollout" if args.mode == "rollout" else "lerobot async inference"
    lerobot = RunSide(out, f"{tool} of {args.policy}", "", run.task, run.task_sha256,
                      f"rendered as `so101-sim eval {_size_flag(args)}`",
                      {s: ours[s] for s in shared}, {}, run_setup())
    result = paired_result(lerobot, replace(run, success={s: run.success[s] for s in shared}))
    for line in summary_lines(result):
        print(line)
    return result


if __name__ == "__main__":
    sys.exit(main())
