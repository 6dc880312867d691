"""What each `so101-sim` subcommand does: parse-free handlers that call the pipeline.

Imports happen inside each handler, so `so101-sim --help` and a mistyped flag stay fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from shlex import quote

from so101_sim.utils.text import counted


def cmd_demo(args: argparse.Namespace) -> int:
    from so101_sim.record.demo import contact_sheet, parse_grid, run_demo
    from so101_sim.sim import IMAGE_SIZE

    if args.grid:  # one PNG of many seeds' first frames
        if args.steps is not None:
            raise ValueError(f"--steps {args.steps} given with --grid, which draws each seed's "
                             "first frame only; drop --steps, or --grid for a rollout")
        sheet = contact_sheet(Path(args.out), args.task, parse_grid(args.grid), args.seed,
                              args.image_size or (240, 320))
        print(f"contact sheet: {sheet}")
        return 0
    paths = run_demo(Path(args.out), steps=240 if args.steps is None else args.steps,
                     image_size=args.image_size or IMAGE_SIZE,
                     seed=args.seed, task=args.task)
    for name, path in paths.items():
        print(f"{name}: {path}")
    print(f"open the scene in MuJoCo's viewer: python -m mujoco.viewer --mjcf="
          f"{quote(str(paths['scene']))} (keyframe seed_{args.seed}: the rollout's start)")
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    from so101_sim.record import record

    try:
        s = record(Path(args.out), args.episodes, task=args.task, seed_start=args.seed_start,
                   image_size=args.image_size, cameras=args.cameras,
                   keep_failures=args.keep_failures,
                   resume=args.resume, workers=args.workers, dart_noise=args.dart_noise,
                   vcodec=args.vcodec, recover=args.recover,
                   grasp_clearance=args.grasp_clearance, backend=args.backend,
                   ray_address=args.ray_address, checkpoint_every=args.checkpoint_every)
    except KeyboardInterrupt:
        print(f"so101-sim record: interrupted; {args.out} holds every completed episode "
              "(continue with --resume)", file=sys.stderr)
        return 130
    reused = f"; {s['reused']} recovered from before a kill" if s.get("reused") else ""
    print(f"{args.out}: {counted(s['episodes'], 'episode')} ({s['new_episodes']} new{reused}; "
          f"{s['successes']}/{s['tried']} seeds succeeded), "
          f"{s['env_steps']} env-steps in {s['seconds']:.1f} s = {s['steps_per_s']:.1f} steps/s")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from so101_sim.record import replay, replay_versions

    dev = replay(Path(args.dataset), args.episode)
    print(f"episode {args.episode}: max |observation.state - re-simulated agent_pos| = {dev:.3g}"
          + replay_versions(Path(args.dataset)))
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from so101_sim.dataset.interrupts import Interrupts
    from so101_sim.train import TrainError, train
    from so101_sim.train.presets import PresetError
    from so101_sim.train.state import TrainingStopped

    # Until the loop takes them over, SIGTERM stops start-up (decoding frames can take
    # minutes) as Ctrl-C does, with the line below instead of a silent death.
    interrupts = Interrupts()
    interrupts.install()
    try:
        r = train(Path(args.dataset), Path(args.out), preset_name=args.preset, steps=args.steps,
                  batch_size=args.batch_size, resume=args.resume, precision=args.precision,
                  device=args.device, threads=args.threads, stop_at=args.stop_at,
                  init_from=Path(args.init_from) if args.init_from else None,
                  keep_frame_cache=args.keep_frame_cache,
                  oversample_closes=args.oversample_closes)
    except (TrainError, PresetError) as e:
        print(f"so101-sim train: error: {e}", file=sys.stderr)
        return 2
    except TrainingStopped as e:
        print(f"so101-sim train: {e}; continue with --resume", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print(f"so101-sim train: {interrupted_train(Path(args.out))}", file=sys.stderr)
        return 130
    finally:
        interrupts.restore()
    print(f"{r.out}: step {r.step}, last loss {r.final_loss:.4f}, {r.samples_per_s:.1f} "
          f"samples/s, {r.wall_s / 60:.1f} min in all; EMA policy in {r.pretrained_dir}")
    return 0


def interrupted_train(out: Path) -> str:
    """What a signal outside the training loop leaves: the run's last checkpoint, or none."""
    from so101_sim.train.state import list_checkpoints

    last = list_checkpoints(out) if out.is_dir() else []
    if last:
        return (f"interrupted; {out} keeps its last checkpoint, {last[-1].name}; continue "
                "with --resume")
    kept = any((out / "frame_cache").glob("*.npy")) if out.is_dir() else False
    return ("interrupted before the first checkpoint; nothing to resume: run the same command "
            "again" + (" (the frames decoded so far are kept in its frame_cache)" if kept else ""))


# eval's flags that --against decides, and those that mean something only with it (the
# package's DEFAULT_TASK and EVAL_SEED_START, spelled out: the CLI imports neither package)
EVAL_DEFAULTS = {"task": "pick_place", "episodes": 50, "seed_start": 100_000}
AGAINST_DEFAULTS = {"margin": 0.0, "indifference": 0.10, "alpha": 0.05}


def resolve_eval_flags(args: argparse.Namespace) -> None:
    """Fill eval's defaults in `args`, refusing a flag the run would ignore: --task,
    --episodes or --seed-start beside --against (RUN decides them), a sequential-test flag
    without --against, or --resume without --out; and an --out it must not write into."""
    if args.resume and args.out is None:
        raise ValueError("--resume given without --out: without it every run gets a new "
                         "outputs/eval/<policy>-<task>-<time> folder, so there is nothing to "
                         "resume; add --out FOLDER, the folder of the run to finish")
    flag = {k: "--" + k.replace("_", "-") for k in (*EVAL_DEFAULTS, *AGAINST_DEFAULTS,
                                                    "max_episodes")}
    if args.against is None:
        given = [flag[k] for k in (*AGAINST_DEFAULTS, "max_episodes")
                 if getattr(args, k) is not None]
        if given:
            raise ValueError(f"{', '.join(given)} given without --against: "
                             "they set the sequential test of `--against RUN`; add --against "
                             "RUN (an earlier eval's --out folder) or drop them")
        if args.task is None:
            from so101_sim.harness.trained_on import default_task

            args.task = default_task(args.policy, EVAL_DEFAULTS["task"])
        for key, value in EVAL_DEFAULTS.items():
            if getattr(args, key) is None:
                setattr(args, key, value)
    else:
        from so101_sim.harness.against import check_out, reference_task
        from so101_sim.harness.compare import load_run

        check_out(args.against, args.out)
        reference = load_run(args.against)
        for key in ("episodes", "seed_start"):
            if getattr(args, key) is not None:
                raise ValueError(f"{flag[key]} {getattr(args, key)} given with --against: "
                                 f"the seeds come from {args.against}, in its order; drop "
                                 f"{flag[key]} (--max-episodes N stops after N of them)")
        args.task = reference_task(reference, args.task)
    for key, value in AGAINST_DEFAULTS.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.against is not None:  # a bad --margin/--alpha/... is named before the policy loads
        from so101_sim.harness.sequential import SequentialPairedTest

        SequentialPairedTest(args.margin, args.indifference, args.alpha, args.max_episodes)
    from so101_sim.harness.suite import names_several_tasks

    if args.out is not None and not names_several_tasks(args.task):
        from so101_sim.harness.results import RunDir

        RunDir(args.out).check_target(args.resume)  # a forgotten --resume: said before loading


def cmd_eval(args: argparse.Namespace) -> int:
    from so101_sim.harness import evaluate, load_policy
    from so101_sim.harness.suite import names_several_tasks
    from so101_sim.utils.collector import startup_objects

    resolve_eval_flags(args)

    options = {k: v for k, v in (("n_action_steps", args.n_action_steps),
                                 ("num_inference_steps", args.inference_steps),
                                 ("noise_scheduler", args.noise_scheduler),
                                 ("temporal_ensemble_coeff", args.temporal_ensemble),
                                 ("batch_size", args.policy_batch),
                                 ("precision", args.precision),
                                 ("camera_map", args.camera_map)) if v is not None}
    suite = names_several_tasks(args.task)  # one table over several tasks
    try:
        checkpoint = _checkpoint_dir(args)
        if checkpoint is not None:
            from so101_sim.harness.suite import task_list
            from so101_sim.harness.trained_on import unseen_task_note

            note = unseen_task_note(checkpoint, task_list(args.task) if suite else [args.task])
            if note:
                print(note)
        if args.backend == "local" and (checkpoint is not None or args.save_rollouts):
            from so101_sim.harness.warmup import start_self_check, warm_eval_workers

            # The env workers' fork server imports on the other core while torch and the
            # policy (or the rollout dataset's lerobot) load here, and the render self-check
            # runs there once it has.
            if (warm_eval_workers(videos=args.videos > 0,
                                  rollouts=args.save_rollouts is not None)
                    and checkpoint is not None
                    and not (suite or args.faithful or args.image_size)):
                start_self_check(checkpoint, args.task, args.camera_map)
        with startup_objects():  # torch's and the checkpoint's objects live to the end
            if args.device != "cpu" and args.policy != "expert" and ":" not in args.policy:
                from so101_sim.utils.devices import resolve_device

                options["device"] = resolve_device(args.device)
            if not suite:
                policy = load_policy(args.policy, task=args.task, **options)
        if suite:
            from so101_sim.harness.suite import evaluate_suite_from_args

            evaluate_suite_from_args(args, options)
            return 0
        common = {"n_envs": args.n_envs, "out_dir": args.out, "videos": args.videos,
                  "image_size": args.image_size, "resume": args.resume,
                  "backend": args.backend, "ray_address": args.ray_address,
                  "save_rollouts": args.save_rollouts, "threads": args.threads,
                  "faithful": args.faithful}
        if args.against:
            from so101_sim.harness.against import evaluate_against

            evaluate_against(policy, args.against, task=args.task,
                             margin=args.margin, indifference=args.indifference,
                             alpha=args.alpha, max_episodes=args.max_episodes, **common,
                             **({"allow_train_seeds": True} if args.allow_train_seeds else {}))
            return 0
        evaluate(policy, task=args.task, episodes=args.episodes, seed_start=args.seed_start,
                 allow_train_seeds=args.allow_train_seeds, **common)
    except KeyboardInterrupt:
        from so101_sim.utils.disk import resume_command

        saved = " and --save-rollouts" if args.save_rollouts else ""
        print(f"so101-sim eval: interrupted; every finished episode is in episodes.jsonl{saved} "
              f"(finish with: {resume_command()})", file=sys.stderr)
        return 130
    return 0


def _checkpoint_dir(args: argparse.Namespace) -> Path | None:
    """The lerobot checkpoint ``so101-sim eval`` will load, if it is there: a directory, or
    the shipped one for a single task. Anything else fails or runs without the warm-up,
    whose GL line would only come before the error."""
    text = args.policy
    if text == "baseline":
        from so101_sim.harness.suite import names_several_tasks

        if names_several_tasks(args.task) or args.against:
            return None
        from so101_sim.harness.baselines import baseline_checkpoint
        from so101_sim.tasks import load_task

        try:
            text = str(baseline_checkpoint(load_task(args.task)))
        except (ValueError, FileNotFoundError):
            return None
    path = Path(text).expanduser()
    return path if (path / "config.json").is_file() else None


def cmd_curve(args: argparse.Namespace) -> int:
    from so101_sim.harness.curve import curve_variant, evaluate_curve, plot_curve
    from so101_sim.tasks import DEFAULT_TASK

    run = Path(args.run)
    if args.task is None:  # the task of the run's demos, as eval's default
        from so101_sim.harness.curve import run_checkpoints
        from so101_sim.harness.trained_on import default_task

        saved = run_checkpoints(run) if run.is_dir() else []
        args.task = default_task(str(saved[-1][1]), DEFAULT_TASK) if saved else DEFAULT_TASK
    options = ({"temporal_ensemble_coeff": args.temporal_ensemble}
               if args.temporal_ensemble is not None else None)
    try:
        rows = evaluate_curve(run, episodes=args.episodes, every=args.every,
                              n_envs=args.n_envs, seed_start=args.seed_start, steps=args.steps,
                              task=args.task, policy_options=options)
    except KeyboardInterrupt:  # every finished episode is on disk, per checkpoint
        print(f"so101-sim curve: interrupted; every finished episode is kept under {run}: run "
              "the same command again to finish the curve", file=sys.stderr)
        return 130
    for r in rows:
        print(f"step {r['step']:>7} ({r['train_hours']:.2f} h): {r['successes']}/"
              f"{r['episodes']} = {100 * r['success']:.1f}% (95% CI {100 * r['ci95'][0]:.1f}-"
              f"{100 * r['ci95'][1]:.1f})")
    # One plot per curve: a variant (e.g. temporal ensembling) never overwrites the
    # checkpoints' own curve.
    task, variant = Path(args.task).stem, curve_variant(options)
    name = "eval_curve" + ("" if task == DEFAULT_TASK else f"_{task}") + \
        (f"-{variant}" if variant else "") + ".png"
    title = f"{task}: closed-loop success" + (f" ({variant})" if variant else "")
    print(f"plot: {plot_curve(rows, run / name, title=title)}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from so101_sim.harness.compare import (
        compare_runs,
        suite_tasks,
        summary_lines,
        write_comparison,
    )

    out = args.out or (Path("outputs/compare") / f"{Path(args.run_a).name}-vs-"
                                                  f"{Path(args.run_b).name}")
    if suite_tasks(args.run_a) is not None or suite_tasks(args.run_b) is not None:
        from so101_sim.harness.compare_suite import (
            compare_suites,
            suite_summary_lines,
            write_suite_comparison,
        )

        r, lines, write = (compare_suites(args.run_a, args.run_b), suite_summary_lines,
                           write_suite_comparison)
    else:
        r, lines, write = compare_runs(args.run_a, args.run_b), summary_lines, write_comparison
    for line in lines(r):
        print(line)
    json_path, md_path = write(r, out)
    print(f"-> {json_path}, {md_path}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from so101_sim.harness.export import export_policy

    try:
        dest = export_policy(Path(args.checkpoint), Path(args.out),
                             [Path(d) for d in args.eval], args.hardware,
                             [Path(d) for d in args.also_eval], replace=args.replace)
    except (FileNotFoundError, ValueError) as e:
        print(f"so101-sim export: error: {e}", file=sys.stderr)
        return 2
    size = sum(f.stat().st_size for f in dest.iterdir()) / 1e6
    print(f"{dest}: {size:.1f} MB (model card {dest / 'README.md'})")
    return 0


def cmd_explain(args: argparse.Namespace) -> int:
    from so101_sim.explain import explain

    ex = explain(Path(args.dataset), args.policy, episode=args.episode, frame=args.frame,
                 k=args.k, out=args.out, preset=args.preset, seed=args.seed)
    n = ex.numbers
    rmse = n["sampling"]["rmse_executed"]
    print(f"loss {n['loss']['mse']:.4f} at k={n['noise']['k']}; sampled chunk vs recorded "
          f"actions: max RMSE {max(rmse) if rmse else float('nan'):.2f} over the executed rows")
    print(f"page: {ex.html_path}  numbers: {ex.json_path}")
    return 0
