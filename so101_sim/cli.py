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


def _demo(args: argparse.Namespace) -> int:
    from so101_sim.demo import run_demo

    paths = run_demo(Path(args.out), steps=args.steps, image_size=args.image_size,
                     seed=args.seed, task=args.task)
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


def _record(args: argparse.Namespace) -> int:
    from so101_sim.recording import record

    try:
        s = record(Path(args.out), args.episodes, task=args.task, seed_start=args.seed_start,
                   image_size=args.image_size, keep_failures=args.keep_failures,
                   resume=args.resume, workers=args.workers)
    except KeyboardInterrupt:
        print(f"so101-sim record: interrupted; {args.out} holds every completed episode "
              "(continue with --resume)", file=sys.stderr)
        return 130
    print(f"{args.out}: {s['episodes']} episodes ({s['new_episodes']} new; "
          f"{s['successes']}/{s['tried']} seeds succeeded), "
          f"{s['env_steps']} env-steps in {s['seconds']:.1f} s = {s['steps_per_s']:.1f} steps/s")
    return 0


def _replay(args: argparse.Namespace) -> int:
    from so101_sim.recording import replay

    dev = replay(Path(args.dataset), args.episode)
    print(f"episode {args.episode}: max |observation.state - re-simulated agent_pos| = {dev:.3g}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="so101-sim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="roll the env with a fixed action sequence; write an mp4 "
                                       "of front|side and one PNG per camera")
    demo.add_argument("--out", default="outputs/demo", help="output folder")
    demo.add_argument("--steps", type=int, default=240)
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--task", default="pick_place", help="task name in envs/ or a .toml path")
    demo.add_argument("--image-size", type=parse_image_size, default=(480, 640),
                      help="HEIGHTxWIDTH of each camera (default 480x640)")
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
    rec.add_argument("--workers", type=int, default=1, help="only 1 is supported for now")
    rec.set_defaults(func=_record)

    rep = sub.add_parser("replay", help="re-simulate a recorded episode from its seed and "
                                        "actions; print the largest state deviation")
    rep.add_argument("dataset", help="dataset folder written by `so101-sim record`")
    rep.add_argument("--episode", type=int, default=0)
    rep.set_defaults(func=_replay)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"so101-sim {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
