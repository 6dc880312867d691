"""The `so101-sim` argument parser: one subcommand per pipeline step, flags checked here."""

from __future__ import annotations

import argparse
import difflib
import sys
from shlex import join

from so101_sim.cli import commands
from so101_sim.cli.arg_types import (
    eval_seed_int,
    nonnegative_int,
    parse_camera_map_arg,
    parse_cameras,
    parse_ensemble_coeff,
    parse_image_size,
    parse_steps,
    positive_int,
)
from so101_sim.cli.lerobot_flags import rewrite_lerobot_flags
from so101_sim.cli.version import ShowVersion


def add_backend_args(p: argparse.ArgumentParser, count_flag: str) -> None:
    """--backend / --ray-address, shared by eval and record."""
    p.add_argument("--backend", choices=("local", "ray"), default="local",
                   help=f"where the {count_flag} envs run: local processes (default) or Ray "
                        "actors (pip install 'so101-sim[ray]'); results are the same")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="with --backend ray: 'auto' or HOST:PORT joins a running cluster "
                        "(`ray start --head` first); omitted, a local Ray runtime is started")
    p.add_argument("--ray-connect-timeout", type=float, default=None, metavar="S",
                   help="seconds to wait for the cluster at --ray-address before giving up "
                        "with a message (default 30)")


def build_parser() -> argparse.ArgumentParser:
    """The `so101-sim` parser, every subcommand on it."""
    return build_parsers()[0]


def parse_command_line(argv: list[str] | None) -> argparse.Namespace:
    """Parse `so101-sim ARGS`; an unknown argument is named in its command's own usage.

    Plain argparse names it under the top-level usage, which lists commands, not the flags
    the user was after, and a misspelt required flag (`eval --polcy P`) only as the flag that
    is missing. `replay --dataset D` (train's spelling) also gets the line that works.
    """
    parser, commands_by_name = build_parsers()
    words = list(sys.argv[1:] if argv is None else argv)
    command = commands_by_name.get(words[0]) if words else None
    if command is not None:  # before argparse, which would first miss the flag meant
        flags = [s for a in command._actions for s in a.option_strings]
        rest = words[1:words.index("--")] if "--" in words else words[1:]
        unknown = [w for w in rest if w.startswith("--")
                   and not any(f.startswith(w.split("=")[0]) for f in flags)]
        if unknown:
            command.error(unrecognized(command, words, unknown))
    args, extras = parser.parse_known_args(words)
    command = commands_by_name[args.command]
    if extras:
        command.error(unrecognized(command, [args.command, *words[1:]], extras))
    for action in command._actions:  # `--out "$OUT"` with OUT unset: eval wrote into the cwd
        value = getattr(args, action.dest, None)
        if value == "" or (isinstance(value, list) and "" in value):
            name = action.option_strings[-1] if action.option_strings else action.dest.upper()
            default = "" if action.required or not action.option_strings else (
                f"; or leave {name} out for its default")
            command.error(f"argument {name}: '' is empty; expected a value (an unset shell "
                          f"variable expands to ''){default}")
    return args


def unrecognized(command: argparse.ArgumentParser, words: list[str], extras: list[str]) -> str:
    """The error for `extras`, with what helps most: for lerobot's flags, the command line in
    this command's spelling; for a positional given as a flag, the command line without the
    flag; else the flag nearest a misspelt one; else --help."""
    name = words[0]
    message = f"unrecognized arguments: {' '.join(extras)}; "
    positionals = {a.dest for a in command._actions if not a.option_strings}
    flags = [s for a in command._actions for s in a.option_strings if s.startswith("--")]
    rewritten = rewrite_lerobot_flags(words, extras)
    if rewritten is not None:  # before spelling, which takes --policy.path for --policy-batch
        return f"{message}so101-sim {name} spells them: {rewritten}"
    for extra in extras:
        flag, _, value = extra.partition("=")
        dest = flag.removeprefix("--").replace("-", "_")
        if flag.startswith("--") and dest in positionals:  # `--dataset D` or `--dataset=D`
            fixed = [value if w == extra else w for w in words if w != extra or value]
            return (f"{message}{dest.upper()} is positional in `so101-sim {name}`, with no "
                    f"flag: so101-sim {join(fixed)}")
        close = difflib.get_close_matches(flag, flags, n=1, cutoff=0.75)
        if extra.startswith("-") and close:
            return f"{message}did you mean {close[0]}? (`so101-sim {name} --help` lists them)"
    return f"{message}`so101-sim {name} --help` lists its arguments"


def build_parsers() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """The top-level parser and each command's own, by name."""
    parser = argparse.ArgumentParser(
        prog="so101-sim", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="SO-101 arm in MuJoCo: record scripted demonstrations, train a policy on "
                    "them,\nevaluate it closed-loop with intervals, compare two evaluations.",
        epilog="a typical run:\n  so101-sim record --episodes 100 --out DATA\n"
               "  so101-sim train --dataset DATA --out RUN\n"
               "  so101-sim eval --policy RUN/pretrained_model --out EVAL\n"
               "  so101-sim compare EVAL OTHER_EVAL\n"
               "`so101-sim COMMAND --help` lists a command's options.")
    parser.add_argument("--version", action=ShowVersion,
                        help="print the versions of so101-sim, MuJoCo, lerobot, torch and "
                             "Gymnasium, and exit")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="roll the env with a fixed action sequence; write an mp4 "
                                       "of front|side and one PNG per camera")
    demo.add_argument("--out", default="outputs/demo",
                      help="output folder (default outputs/demo)")
    demo.add_argument("--steps", type=positive_int, default=None,
                      help="env steps of the rollout (default 240; not with --grid)")
    demo.add_argument("--seed", type=nonnegative_int, default=0,
                      help="reset seed of the rollout; with --grid, of the first tile (default 0)")
    demo.add_argument("--task", default="pick_place",
                      help="task name in envs/ or a .toml path (default pick_place)")
    demo.add_argument("--image-size", type=parse_image_size, default=None,
                      help="HEIGHTxWIDTH of each camera (default 480x640; 240x320 with --grid)")
    demo.add_argument("--grid", default=None, metavar="ROWSxCOLS",
                      help="instead of a rollout, write one PNG of the first front frame of "
                           "ROWS*COLS seeds from --seed (e.g. --task pick_place_dr --grid 4x4)")
    demo.set_defaults(func=commands.cmd_demo)

    rec = sub.add_parser("record", help="record scripted-expert demonstrations as a "
                                        "LeRobotDataset v3 (training seeds only)")
    rec.add_argument("--task", default=None,
                     help="task name in envs/ or a .toml path (default pick_place; a resumed "
                          "dataset keeps its own)")
    rec.add_argument("--episodes", type=positive_int, required=True,
                     help="episodes wanted in the dataset")
    rec.add_argument("--out", required=True, help="dataset folder (the LeRobotDataset root)")
    rec.add_argument("--seed-start", type=nonnegative_int, default=0,
                     help="first reset seed (0..99999)")
    rec.add_argument("--image-size", type=parse_image_size, default=None,
                     help="HEIGHTxWIDTH of each camera, even sides (stored as 4:2:0 video; "
                          "default 480x640; a resumed dataset keeps its own)")
    rec.add_argument("--cameras", type=parse_cameras, default=None,
                     help="cameras to record, comma-separated from front, side, wrist "
                          "(default the task's: front,side); e.g. front,side,wrist")
    rec.add_argument("--keep-failures", action="store_true",
                     help="also keep episodes the expert failed")
    rec.add_argument("--resume", action="store_true",
                     help="continue an existing dataset up to --episodes without repeating a seed")
    rec.add_argument("--workers", type=positive_int, default=1,
                     help="workers that simulate, render and encode in parallel (processes, "
                          "or Ray actors with --backend ray; one per CPU core is best; default "
                          "1); episodes are still stored in seed order")
    rec.add_argument("--dart-noise", type=float, default=0.0, metavar="STD",
                     help="DART noise: execute the expert's action plus Gaussian noise of this "
                          "std (degrees; gripper 0..100 units) while `action` keeps the clean "
                          "label; executed actions go to `action_executed` (default 0: off)")
    rec.add_argument("--recover", action="store_true",
                     help="the expert watches the cube and retries a missed grasp, a dropped "
                          "cube or a cube left off the target (recoveries in the demos; use "
                          "with --dart-noise so some first attempts fail)")
    rec.add_argument("--grasp-clearance", type=float, default=None, metavar="M",
                     help="gap (m) between the fixed finger pad and the cube when the expert "
                          "grasps (default 0.004; 0.012 centres the cube in the open gripper "
                          "and tolerates ~2x the position error)")
    rec.add_argument("--vcodec", choices=["h264", "libsvtav1"], default=None,
                     help="video codec of a new dataset (default h264: about half the CPU of "
                          "AV1 per frame; a resumed dataset keeps its own)")
    rec.add_argument("--checkpoint-every", type=positive_int, default=50, metavar="N",
                     help="finalize the dataset every N episodes (default 50). A kill loses "
                          "no finished episode either way (--resume recovers them); this "
                          "bounds the recovery work and the spooled episodes on disk")
    add_backend_args(rec, "--workers")
    rec.set_defaults(func=commands.cmd_record)

    rep = sub.add_parser("replay", help="re-simulate a recorded episode from its seed and "
                                        "actions; print the largest state deviation")
    rep.add_argument("dataset", help="dataset folder written by `so101-sim record`")
    rep.add_argument("--episode", type=nonnegative_int, default=0,
                     help="episode index in the dataset (default 0)")
    rep.set_defaults(func=commands.cmd_replay)

    tr = sub.add_parser("train", help="train a Diffusion Policy (or ACT) preset on a recorded "
                                      "dataset (EMA weights, lerobot checkpoint format)")
    tr.add_argument("--preset", default="cpu",
                    help="preset name in policy/presets (cpu, seed, act) or a .toml path "
                         "(default cpu)")
    tr.add_argument("--dataset", required=True, help="LeRobotDataset folder (so101-sim record)")
    tr.add_argument("--out", required=True, help="run folder (checkpoints, log, final policy)")
    tr.add_argument("--steps", type=positive_int, default=None,
                    help="total steps (default: preset); with --resume, a larger value "
                         "stretches the lr schedule from the checkpoint on")
    tr.add_argument("--batch-size", type=positive_int, default=None, help="default: preset")
    tr.add_argument("--stop-at", type=positive_int, default=None, metavar="STEP",
                    help="pause at this step with a checkpoint; the schedule stays sized for "
                         "--steps, so --resume later continues the same run (for comparing runs "
                         "at equal steps)")
    tr.add_argument("--resume", action="store_true",
                    help="continue from the last checkpoint in --out, exactly")
    tr.add_argument("--keep-frame-cache", action="store_true",
                    help="keep the decoded frames (--out/frame_cache, GBs) after the last step; "
                         "by default they are deleted then (a pause or --stop-at keeps them)")
    tr.add_argument("--init-from", default=None, metavar="CHECKPOINT",
                    help="start a new run from this checkpoint's weights (fine-tuning, e.g. "
                         "policy/suite_diffusion on more demos); same preset architecture, "
                         "or a Diffusion one with more cameras or keypoints (they start at "
                         "zero weight); the optimiser, schedule and normalisation start fresh")
    tr.add_argument("--oversample-closes", type=float, default=None, metavar="FACTOR",
                    help="draw the frames around each close of the gripper (1.5 s before to "
                         "0.5 s after) FACTOR times as often as the rest, for policies whose "
                         "misses are imprecise grasps (default: every frame alike)")
    tr.add_argument("--threads", type=positive_int, default=None,
                    help="torch CPU threads, fixed and bitwise repeatable (default on CPU: "
                         "all cores when idle; with another job busy, the batch in one part "
                         "per core, one thread each)")
    tr.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                    help="bf16: autocast matmuls/convs to bfloat16 (1.45x faster per step on "
                         "AMX/AVX512-BF16 CPUs; weights, optimiser and EMA stay fp32); auto "
                         "(default): bf16 on such CPUs, else fp32 (also on CUDA, where bf16 was "
                         "slower at the presets' batch sizes)")
    tr.add_argument("--device", choices=("auto", "cpu", "cuda", "mps"), default="auto",
                    help="auto (default): cuda, then mps, then cpu")
    tr.set_defaults(func=commands.cmd_train)

    cu = sub.add_parser("curve", help="evaluate a training run's saved checkpoints on the same "
                                      "evaluation seeds: success against step and hours")
    cu.add_argument("run", help="the --out folder of `so101-sim train`")
    cu.add_argument("--episodes", type=positive_int, default=32,
                    help="seeds per checkpoint (default 32)")
    cu.add_argument("--every", type=nonnegative_int, default=0,
                    help="only checkpoints whose step is a multiple of this (default: all)")
    cu.add_argument("--n-envs", type=positive_int, default=16,
                    help="env workers per checkpoint (default 16, as eval: two forwards of 8)")
    cu.add_argument("--seed-start", type=eval_seed_int, default=100_000,
                    help="first evaluation seed (default 100000)")
    cu.add_argument("--steps", default=None, type=parse_steps,
                    help="only these checkpoint steps, comma-separated (e.g. 8000,12000)")
    cu.add_argument("--task", default=None, help="task to evaluate on (default its demos', "
                    "else pick_place; a multi-task run has one curve per task)")
    cu.add_argument("--temporal-ensemble", type=parse_ensemble_coeff, default=None,
                    metavar="COEFF", help="evaluate with temporal ensembling (as `eval "
                    "--temporal-ensemble`); a separate curve from the checkpoints' own setting")
    cu.set_defaults(func=commands.cmd_curve)

    ex = sub.add_parser("export", help="copy a trained checkpoint to a shippable folder: fp16 "
                                       "weights and a model card with harness numbers")
    ex.add_argument("checkpoint", help="a checkpoints/step_*/pretrained_model folder")
    ex.add_argument("--out", default="policy/pick_place_diffusion",
                    help="the shippable folder (default policy/pick_place_diffusion, the "
                         "shipped policy: overwriting another policy needs --replace)")
    ex.add_argument("--eval", action="append", default=[], metavar="DIR",
                    help="a `so101-sim eval --out` folder whose eval_info.json goes into the "
                         "card; repeat it once per task for a multi-task checkpoint (or give "
                         "one `--task a,b` suite folder)")
    ex.add_argument("--also-eval", action="append", default=[], metavar="DIR",
                    help="more eval folders of the same checkpoint (e.g. the direct-render "
                         "path) shown in the card beside --eval; repeatable")
    ex.add_argument("--hardware", default="2-core CPU (no GPU)",
                    help="what trained and evaluated it, for the card's table (default "
                         "'2-core CPU (no GPU)')")
    ex.add_argument("--replace", action="store_true",
                    help="overwrite an --out that holds another policy (refused otherwise; "
                         "exporting the same checkpoint again, e.g. with its eval, needs no "
                         "flag)")
    ex.set_defaults(func=commands.cmd_export)

    ev = sub.add_parser("eval", help="evaluate a policy closed-loop on evaluation seeds: "
                                     "success rate with interval, failure modes, videos, report")
    ev.add_argument("--policy", required=True,
                    help="'expert', a lerobot checkpoint directory (config.json, "
                         "model.safetensors, saved processors; read as data: processor steps "
                         "must be ones lerobot registers) or 'package.module:factory', which "
                         "IMPORTS AND RUNS that Python code: use it only for your own code")
    ev.add_argument("--task", default=None,
                    help="task name in envs/ or a .toml path (default: the checkpoint's demos', "
                         "else pick_place; with --against, RUN's); several as a,b,c or 'all' "
                         "(one folder per task under --out, one table, eval_info.json per task)")
    ev.add_argument("--episodes", type=positive_int, default=None,
                    help="seeds to run (default 50; with --against, RUN's)")
    ev.add_argument("--n-envs", type=positive_int, default=16,
                    help="env workers (default 16: two policy forwards of 8, so one half steps "
                         "while the policy runs the other's): processes, or Ray actors with "
                         "--backend ray; results per seed depend on neither")
    ev.add_argument("--seed-start", type=nonnegative_int, default=None, help="first seed "
                    "(default 100000; training seeds are below it; with --against, RUN's)")
    ev.add_argument("--allow-train-seeds", action="store_true",
                    help="measure on training seeds on purpose: --seed-start below 100000, "
                         "or seeds of rollouts the checkpoint was trained on")
    ev.add_argument("--out", default=None,
                    help="output folder (default outputs/eval/<policy>-<task>-<time>)")
    ev.add_argument("--videos", type=nonnegative_int, default=2,
                    help="mp4s of the first V episodes (default 2; 0 for none)")
    ev.add_argument("--image-size", type=parse_image_size, default=None,
                    help="render size HEIGHTxWIDTH (default: the smallest size whose frames, "
                         "resized like training, match the faithful ones within a tolerance "
                         "checked at start; the policy's input size renders directly, any "
                         "other size keeps the training data's mesh detail)")
    ev.add_argument("--faithful", action="store_true",
                    help="render at the training data's size (so101_sim_train.json) and resize "
                         "like training did: exactly what the policy was trained on, slower")
    ev.add_argument("--against", default=None, metavar="RUN",
                    help="an earlier `so101-sim eval --out` folder: run its seeds in order and "
                         "stop as soon as a sequential paired test decides 'worse' or 'not "
                         "worse' (anytime-valid; the task and seeds come from RUN, "
                         "--max-episodes caps them)")
    ev.add_argument("--margin", type=float, default=None, metavar="M",
                    help="with --against: 'worse' means below RUN's rate by more than M "
                         "(a fraction, default 0)")
    ev.add_argument("--indifference", type=float, default=None, metavar="D",
                    help="with --against: 'not worse' rules out a drop of M + D or more "
                         "(default 0.10, the regression the check is sized for)")
    ev.add_argument("--alpha", type=float, default=None,
                    help="with --against: each wrong verdict's probability bound (default 0.05)")
    ev.add_argument("--max-episodes", type=positive_int, default=None, metavar="N",
                    help="with --against: stop 'undecided' after N seeds (default: all of RUN's)")
    ev.add_argument("--resume", action="store_true",
                    help="finish an interrupted evaluation in --out, or extend it to more "
                         "--episodes (the seeds already run are kept)")
    ev.add_argument("--n-action-steps", type=positive_int, default=None,
                    help="actions executed per chunk (default: the checkpoint's)")
    ev.add_argument("--inference-steps", type=positive_int, default=None,
                    help="diffusion denoising steps (default: the checkpoint's)")
    ev.add_argument("--noise-scheduler", choices=["DDIM", "DDPM"], default=None,
                    help="diffusion sampler (default: the checkpoint's)")
    ev.add_argument("--temporal-ensemble", type=parse_ensemble_coeff, default=None,
                    metavar="COEFF",
                    help="temporal ensembling with this coefficient (0.01 in ACT's paper): "
                         "a forward every step, chunks averaged with weights exp(-COEFF*i) "
                         "(ACT; a Diffusion Policy averages its horizon-To+1 actions); "
                         "'off' runs an ensembling checkpoint chunk-wise (with "
                         "--n-action-steps); default: the checkpoint's (lerobot-eval's "
                         "--policy.temporal_ensemble_coeff)")
    ev.add_argument("--threads", type=positive_int, default=None,
                    help="torch CPU threads for the policy's forwards (default: half the cores, "
                         "at least 1: the env workers render on the rest, and a busy "
                         "neighbour cannot stall a thread pool)")
    ev.add_argument("--device", choices=("auto", "cpu", "cuda", "mps"), default="auto",
                    help="where policy forwards run (default auto: cuda, then mps, then cpu); "
                         "envs always run on CPU workers")
    ev.add_argument("--precision", choices=("fp32", "bf16"), default=None,
                    help="policy forwards in fp32 (default) or bfloat16 autocast (faster on "
                         "CPUs with AVX512-BF16/AMX; outcomes can differ on a few seeds, see "
                         "benchmarks/README.md)")
    ev.add_argument("--policy-batch", type=positive_int, default=None,
                    help="rows per policy forward, padded (default 8; 1 = one env per "
                         "forward; on a GPU, the --n-envs value is faster)")
    ev.add_argument("--camera-map", type=parse_camera_map_arg, default=None,
                    metavar="POLICY_CAM=ENV_CAM,...",
                    help="feed env cameras (front, side) to policy camera inputs named after "
                         "another rig, e.g. top=front,wrist=side; the summary and report "
                         "state the mapping")
    ev.add_argument("--save-rollouts", default=None, metavar="DIR",
                    help="also write every evaluated episode to DIR as a LeRobotDataset (both "
                         "cameras as video at the render size, executed actions, seed, "
                         "success, failure mode); renders every step, so slower")
    add_backend_args(ev, "--n-envs")
    ev.set_defaults(func=commands.cmd_eval)

    cmp = sub.add_parser("compare", help="compare two eval folders seed by seed: both rates, "
                                         "the paired table, exact McNemar p, the difference "
                                         "with its interval")
    cmp.add_argument("run_a", help="an `so101-sim eval --out` folder (A); two `eval --task "
                                   "a,b` folders are compared task by task, then pooled")
    cmp.add_argument("run_b", help="another one over the same seeds and task (B)")
    cmp.add_argument("--out", default=None, help="folder for compare.json and compare.md "
                                                 "(default outputs/compare/<A>-vs-<B>)")
    cmp.set_defaults(func=commands.cmd_compare)

    xp = sub.add_parser("explain", help="trace one training example through a Diffusion "
                                        "Policy, step by step with real numbers: one "
                                        "self-contained HTML page + JSON")
    xp.add_argument("--dataset", required=True, help="LeRobotDataset folder (so101-sim record)")
    xp.add_argument("--policy", default=None,
                    help="lerobot diffusion checkpoint folder (read as data: processor steps "
                         "must be ones lerobot registers); default: a fresh, untrained "
                         "--preset policy with this dataset's normalisation stats")
    xp.add_argument("--preset", default=None, help="diffusion preset of the fresh policy "
                    "traced when there is no --policy (default seed)")
    xp.add_argument("--episode", type=nonnegative_int, default=0,
                    help="episode index in the dataset (default 0)")
    xp.add_argument("--frame", type=int, default=5,
                    help="current frame t within the episode (default 5: frames 4 and 5 are "
                         "observed, as in the walkthrough)")
    xp.add_argument("--k", type=nonnegative_int, default=25,
                    help="diffusion step at which noise is added for the loss (default 25)")
    xp.add_argument("--seed", type=nonnegative_int, default=0,
                    help="seed of the noise (loss and sampling) and of a fresh policy")
    xp.add_argument("--out", default=None, help="output folder for explain.html and "
                    "explain.json (default outputs/explain/<policy>-ep<E>-f<F>)")
    xp.set_defaults(func=commands.cmd_explain)
    return parser, dict(sub.choices)
