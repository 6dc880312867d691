"""`so101-sim` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def parse_image_size(text: str) -> tuple[int, int]:
    """"480x640" -> (480, 640) (height x width)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"image size {text!r} is invalid; expected HEIGHTxWIDTH, e.g. 480x640") from None
    if not (16 <= h <= 2048 and 16 <= w <= 2048):
        raise argparse.ArgumentTypeError(f"image size {text!r} out of range; each side 16..2048")
    return h, w


def parse_camera_map_arg(text: str) -> dict[str, str]:
    """argparse type for --camera-map (see so101_sim.harness.camera_map)."""
    from so101_sim.harness.camera_map import parse_camera_map

    try:
        return parse_camera_map(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _demo(args: argparse.Namespace) -> int:
    from so101_sim.demo import contact_sheet, parse_grid, run_demo

    if args.grid:  # one PNG of many seeds' first frames
        sheet = contact_sheet(Path(args.out), args.task, parse_grid(args.grid), args.seed,
                              args.image_size or (240, 320))
        print(f"contact sheet: {sheet}")
        return 0
    paths = run_demo(Path(args.out), steps=args.steps, image_size=args.image_size or (480, 640),
                     seed=args.seed, task=args.task)
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


def _record(args: argparse.Namespace) -> int:
    from so101_sim.recording import record

    try:
        s = record(Path(args.out), args.episodes, task=args.task, seed_start=args.seed_start,
                   image_size=args.image_size, keep_failures=args.keep_failures,
                   resume=args.resume, workers=args.workers, dart_noise=args.dart_noise,
                   vcodec=args.vcodec, recover=args.recover,
                   grasp_clearance=args.grasp_clearance, backend=args.backend,
                   ray_address=args.ray_address, checkpoint_every=args.checkpoint_every)
    except KeyboardInterrupt:
        print(f"so101-sim record: interrupted; {args.out} holds every completed episode "
              "(continue with --resume)", file=sys.stderr)
        return 130
    reused = f"; {s['reused']} recovered from before a kill" if s.get("reused") else ""
    print(f"{args.out}: {s['episodes']} episodes ({s['new_episodes']} new{reused}; "
          f"{s['successes']}/{s['tried']} seeds succeeded), "
          f"{s['env_steps']} env-steps in {s['seconds']:.1f} s = {s['steps_per_s']:.1f} steps/s")
    return 0


def _replay(args: argparse.Namespace) -> int:
    from so101_sim.recording import replay

    dev = replay(Path(args.dataset), args.episode)
    print(f"episode {args.episode}: max |observation.state - re-simulated agent_pos| = {dev:.3g}")
    return 0


def _train(args: argparse.Namespace) -> int:
    from so101_sim.presets import PresetError
    from so101_sim.trainer import TrainError, train

    try:
        r = train(Path(args.dataset), Path(args.out), preset_name=args.preset, steps=args.steps,
                  batch_size=args.batch_size, resume=args.resume, precision=args.precision,
                  device=args.device, threads=args.threads, stop_at=args.stop_at)
    except (TrainError, PresetError) as e:
        print(f"so101-sim train: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        print(f"so101-sim train: {e}; continue with --resume", file=sys.stderr)
        return 130
    print(f"{r.out}: step {r.step}, last loss {r.final_loss:.4f}, {r.samples_per_s:.1f} "
          f"samples/s, {r.wall_s / 60:.1f} min in all; EMA policy in {r.pretrained_dir}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from so101_sim.harness import evaluate, load_policy

    options = {k: v for k, v in (("n_action_steps", args.n_action_steps),
                                 ("num_inference_steps", args.inference_steps),
                                 ("noise_scheduler", args.noise_scheduler),
                                 ("batch_size", args.policy_batch),
                                 ("camera_map", args.camera_map)) if v is not None}
    try:
        if args.device != "cpu" and args.policy != "expert" and ":" not in args.policy:
            from so101_sim.devices import resolve_device

            options["device"] = resolve_device(args.device)
        if "," in args.task or args.task == "all":  # one table over several tasks
            from so101_sim.harness.suite import evaluate_suite_from_args

            evaluate_suite_from_args(args, options)
            return 0
        policy = load_policy(args.policy, task=args.task, **options)
        evaluate(policy, task=args.task, episodes=args.episodes, n_envs=args.n_envs,
                 seed_start=args.seed_start, out_dir=args.out, videos=args.videos,
                 image_size=args.image_size, resume=args.resume,
                 allow_train_seeds=args.allow_train_seeds, backend=args.backend,
                 ray_address=args.ray_address, save_rollouts=args.save_rollouts,
                 threads=args.threads)
    except KeyboardInterrupt:
        saved = " and --save-rollouts" if args.save_rollouts else ""
        print(f"so101-sim eval: interrupted; every finished episode is in episodes.jsonl{saved} "
              "(finish with the same arguments plus --resume)", file=sys.stderr)
        return 130
    return 0


def _curve(args: argparse.Namespace) -> int:
    from so101_sim.harness.curve import evaluate_curve, plot_curve

    run = Path(args.run)
    rows = evaluate_curve(run, episodes=args.episodes, every=args.every, n_envs=args.n_envs,
                          seed_start=args.seed_start)
    for r in rows:
        print(f"step {r['step']:>7} ({r['train_hours']:.2f} h): {r['successes']}/"
              f"{r['episodes']} = {100 * r['success']:.1f}% (95% CI {100 * r['ci95'][0]:.1f}-"
              f"{100 * r['ci95'][1]:.1f})")
    print(f"plot: {plot_curve(rows, run / 'eval_curve.png')}")
    return 0


def _compare(args: argparse.Namespace) -> int:
    from so101_sim.harness.compare import compare_runs, summary_lines, write_comparison

    r = compare_runs(args.run_a, args.run_b)
    out = args.out or (Path("outputs/compare") / f"{Path(args.run_a).name}-vs-"
                                                  f"{Path(args.run_b).name}")
    for line in summary_lines(r):
        print(line)
    json_path, md_path = write_comparison(r, out)
    print(f"-> {json_path}, {md_path}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from so101_sim.export import export_policy

    try:
        dest = export_policy(Path(args.checkpoint), Path(args.out),
                             Path(args.eval) if args.eval else None, args.hardware,
                             [Path(d) for d in args.also_eval])
    except FileNotFoundError as e:
        print(f"so101-sim export: {e}", file=sys.stderr)
        return 2
    size = sum(f.stat().st_size for f in dest.iterdir()) / 1e6
    print(f"{dest}: {size:.1f} MB (model card {dest / 'README.md'})")
    return 0


def _explain(args: argparse.Namespace) -> int:
    from so101_sim.explain import explain

    ex = explain(Path(args.dataset), args.policy, episode=args.episode, frame=args.frame,
                 k=args.k, out=args.out, preset=args.preset, seed=args.seed)
    n = ex.numbers
    rmse = n["sampling"]["rmse_executed"]
    print(f"loss {n['loss']['mse']:.4f} at k={n['noise']['k']}; sampled chunk vs recorded "
          f"actions: max RMSE {max(rmse) if rmse else float('nan'):.2f} over the executed rows")
    print(f"page: {ex.html_path}  numbers: {ex.json_path}")
    return 0


def add_backend_args(p: argparse.ArgumentParser, count_flag: str) -> None:
    """--backend / --ray-address, shared by eval and record."""
    p.add_argument("--backend", choices=("local", "ray"), default="local",
                   help=f"where the {count_flag} envs run: local processes (default) or Ray "
                        "actors (pip install 'so101-sim[ray]'); results are the same")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="with --backend ray: 'auto' or HOST:PORT joins a running cluster "
                        "(`ray start --head` first); omitted, a local Ray runtime is started")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="so101-sim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="roll the env with a fixed action sequence; write an mp4 "
                                       "of front|side and one PNG per camera")
    demo.add_argument("--out", default="outputs/demo", help="output folder")
    demo.add_argument("--steps", type=int, default=240)
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--task", default="pick_place", help="task name in envs/ or a .toml path")
    demo.add_argument("--image-size", type=parse_image_size, default=None,
                      help="HEIGHTxWIDTH of each camera (default 480x640; 240x320 with --grid)")
    demo.add_argument("--grid", default=None, metavar="ROWSxCOLS",
                      help="instead of a rollout, write one PNG of the first front frame of "
                           "ROWS*COLS seeds from --seed (e.g. --task pick_place_dr --grid 4x4)")
    demo.set_defaults(func=_demo)

    rec = sub.add_parser("record", help="record scripted-expert demonstrations as a "
                                        "LeRobotDataset v3 (training seeds only)")
    rec.add_argument("--task", default="pick_place", help="task name in envs/ or a .toml path")
    rec.add_argument("--episodes", type=int, required=True, help="episodes wanted in the dataset")
    rec.add_argument("--out", required=True, help="dataset folder (the LeRobotDataset root)")
    rec.add_argument("--seed-start", type=int, default=0, help="first reset seed (0..99999)")
    rec.add_argument("--image-size", type=parse_image_size, default=(480, 640),
                     help="HEIGHTxWIDTH of each camera (default 480x640)")
    rec.add_argument("--keep-failures", action="store_true",
                     help="also keep episodes the expert failed")
    rec.add_argument("--resume", action="store_true",
                     help="continue an existing dataset up to --episodes without repeating a seed")
    rec.add_argument("--workers", type=int, default=1,
                     help="workers that simulate, render and encode in parallel (processes, "
                          "or Ray actors with --backend ray; one per CPU core is best); "
                          "episodes are still stored in seed order")
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
    rec.add_argument("--checkpoint-every", type=int, default=50, metavar="N",
                     help="finalize the dataset every N episodes (default 50). A kill loses "
                          "no finished episode either way (--resume recovers them); this "
                          "bounds the recovery work and the spooled episodes on disk")
    add_backend_args(rec, "--workers")
    rec.set_defaults(func=_record)

    rep = sub.add_parser("replay", help="re-simulate a recorded episode from its seed and "
                                        "actions; print the largest state deviation")
    rep.add_argument("dataset", help="dataset folder written by `so101-sim record`")
    rep.add_argument("--episode", type=int, default=0)
    rep.set_defaults(func=_replay)

    tr = sub.add_parser("train", help="train a Diffusion Policy preset on a recorded dataset "
                                      "(EMA weights, lerobot checkpoint format)")
    tr.add_argument("--preset", default="cpu", help="preset name in policy/presets (cpu, seed) "
                                                    "or a .toml path")
    tr.add_argument("--dataset", required=True, help="LeRobotDataset folder (so101-sim record)")
    tr.add_argument("--out", required=True, help="run folder (checkpoints, log, final policy)")
    tr.add_argument("--steps", type=int, default=None, help="total steps (default: preset)")
    tr.add_argument("--batch-size", type=int, default=None, help="default: preset")
    tr.add_argument("--stop-at", type=int, default=None, metavar="STEP",
                    help="pause at this step with a checkpoint; the schedule stays sized for "
                         "--steps, so --resume later continues the same run (for comparing runs "
                         "at equal steps)")
    tr.add_argument("--resume", action="store_true",
                    help="continue from the last checkpoint in --out, exactly")
    tr.add_argument("--threads", type=int, default=None,
                    help="torch CPU threads, fixed and bitwise repeatable (default on CPU: "
                         "all cores when idle; with another job busy, the batch in one part "
                         "per core, one thread each)")
    tr.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                    help="bf16: autocast matmuls/convs to bfloat16 (1.45x faster per step on "
                         "AMX/AVX512-BF16 CPUs; weights, optimiser and EMA stay fp32); auto "
                         "(default): bf16 where the device has fast bf16, else fp32")
    tr.add_argument("--device", choices=("auto", "cpu", "cuda", "mps"), default="auto",
                    help="auto (default): cuda, then mps, then cpu")
    tr.set_defaults(func=_train)

    cu = sub.add_parser("curve", help="evaluate a training run's saved checkpoints on the same "
                                      "evaluation seeds: success against step and hours")
    cu.add_argument("run", help="the --out folder of `so101-sim train`")
    cu.add_argument("--episodes", type=int, default=32, help="seeds per checkpoint")
    cu.add_argument("--every", type=int, default=0,
                    help="only checkpoints whose step is a multiple of this (default: all)")
    cu.add_argument("--n-envs", type=int, default=8)
    cu.add_argument("--seed-start", type=int, default=100_000)
    cu.set_defaults(func=_curve)

    ex = sub.add_parser("export", help="copy a trained checkpoint to a shippable folder: fp16 "
                                       "weights and a model card with harness numbers")
    ex.add_argument("checkpoint", help="a checkpoints/step_*/pretrained_model folder")
    ex.add_argument("--out", default="policy/pick_place_diffusion")
    ex.add_argument("--eval", default=None, help="a `so101-sim eval --out` folder whose "
                                                 "eval_info.json goes into the card")
    ex.add_argument("--also-eval", action="append", default=[], metavar="DIR",
                    help="more eval folders of the same checkpoint (e.g. the direct-render "
                         "path) shown in the card beside --eval; repeatable")
    ex.add_argument("--hardware", default="2-core CPU (no GPU)")
    ex.set_defaults(func=_export)

    ev = sub.add_parser("eval", help="evaluate a policy closed-loop on evaluation seeds: "
                                     "success rate with interval, failure modes, videos, report")
    ev.add_argument("--policy", required=True,
                    help="'expert', a lerobot checkpoint directory (config.json, "
                         "model.safetensors, saved processors; read as data: processor steps "
                         "must be ones lerobot registers) or 'package.module:factory', which "
                         "IMPORTS AND RUNS that Python code: use it only for your own code")
    ev.add_argument("--task", default="pick_place",
                    help="task name in envs/ or a .toml path; several as a,b,c or 'all' "
                         "(one folder per task under --out, one table, eval_info.json "
                         "grouped per task)")
    ev.add_argument("--episodes", type=int, default=50)
    ev.add_argument("--n-envs", type=int, default=16,
                    help="env workers (default 16: two policy forwards of 8, so one half steps "
                         "while the policy runs the other's): processes, or Ray actors with "
                         "--backend ray; results per seed depend on neither")
    ev.add_argument("--seed-start", type=int, default=100_000,
                    help="first seed (default 100000; training seeds are below it)")
    ev.add_argument("--allow-train-seeds", action="store_true",
                    help="allow --seed-start below 100000 (measuring on training seeds)")
    ev.add_argument("--out", default=None,
                    help="output folder (default outputs/eval/<policy>-<task>-<time>)")
    ev.add_argument("--videos", type=int, default=2, help="mp4s of the first V episodes")
    ev.add_argument("--image-size", type=parse_image_size, default=None,
                    help="render size HEIGHTxWIDTH (default: the checkpoint's training data size "
                         "from so101_sim_train.json, then resized like training; the policy's "
                         "input size renders directly, faster)")
    ev.add_argument("--resume", action="store_true",
                    help="finish an interrupted evaluation in --out")
    ev.add_argument("--n-action-steps", type=int, default=None,
                    help="actions executed per chunk (default: the checkpoint's)")
    ev.add_argument("--inference-steps", type=int, default=None,
                    help="diffusion denoising steps (default: the checkpoint's)")
    ev.add_argument("--noise-scheduler", choices=["DDIM", "DDPM"], default=None,
                    help="diffusion sampler (default: the checkpoint's)")
    ev.add_argument("--threads", type=int, default=None,
                    help="torch CPU threads for the policy's forwards (default: half the cores, "
                         "at least 1: the env workers render on the rest, and a busy "
                         "neighbour cannot stall a thread pool)")
    ev.add_argument("--device", choices=("auto", "cpu", "cuda", "mps"), default="auto",
                    help="where policy forwards run (default auto: cuda, then mps, then cpu); "
                         "envs always run on CPU workers")
    ev.add_argument("--policy-batch", type=int, default=None,
                    help="rows per policy forward, padded (default 8; 1 = one env per forward)")
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
    ev.set_defaults(func=_eval)

    cmp = sub.add_parser("compare", help="compare two eval folders seed by seed: both rates, "
                                         "the paired table, exact McNemar p, the difference "
                                         "with its interval")
    cmp.add_argument("run_a", help="an `so101-sim eval --out` folder (A)")
    cmp.add_argument("run_b", help="another one over the same seeds and task (B)")
    cmp.add_argument("--out", default=None, help="folder for compare.json and compare.md "
                                                 "(default outputs/compare/<A>-vs-<B>)")
    cmp.set_defaults(func=_compare)

    xp = sub.add_parser("explain", help="trace one training example through a Diffusion "
                                        "Policy, step by step with real numbers: one "
                                        "self-contained HTML page + JSON")
    xp.add_argument("--dataset", required=True, help="LeRobotDataset folder (so101-sim record)")
    xp.add_argument("--policy", default=None,
                    help="lerobot diffusion checkpoint folder (read as data: processor steps "
                         "must be ones lerobot registers); default: a fresh, untrained "
                         "--preset policy with this dataset's normalisation stats")
    xp.add_argument("--preset", default="seed",
                    help="preset of the fresh policy when no --policy (default seed)")
    xp.add_argument("--episode", type=int, default=0)
    xp.add_argument("--frame", type=int, default=5,
                    help="current frame t within the episode (default 5: frames 4 and 5 are "
                         "observed, as in the walkthrough)")
    xp.add_argument("--k", type=int, default=25,
                    help="diffusion step at which noise is added for the loss (default 25)")
    xp.add_argument("--seed", type=int, default=0,
                    help="seed of the noise (loss and sampling) and of a fresh policy")
    xp.add_argument("--out", default=None, help="output folder for explain.html and "
                                                "explain.json (default "
                                                "outputs/explain/<policy>-ep<E>-f<F>)")
    xp.set_defaults(func=_explain)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except PermissionError as exc:
        print(f"so101-sim {args.command}: error: cannot write or read {exc.filename}: "
              "permission denied; choose a folder you own (e.g. under your home) for --out",
              file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"so101-sim {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
