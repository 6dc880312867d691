"""Rollout-harness speed, and the harness against lerobot-eval on the same checkpoint and seeds.

    .venv/bin/python benchmarks/bench_eval.py CHECKPOINT [--episodes 50] [--n-envs 16]
    .venv/bin/python benchmarks/bench_eval.py CHECKPOINT --compare-lerobot
    .venv/bin/python benchmarks/bench_eval.py CHECKPOINT --paths --bf16 --episodes 200
    .venv/bin/python benchmarks/bench_eval.py CHECKPOINT --plain-kernels --episodes 200
    .venv/bin/python benchmarks/bench_eval.py CHECKPOINT --startup 3 --episodes 16
    .venv/bin/python benchmarks/bench_eval.py CHECKPOINT --tail 2 --episodes 48 --n-envs 12
    .venv/bin/python benchmarks/bench_eval.py CHECKPOINT --split 2 --episodes 32 --n-envs 8
    .venv/bin/python benchmarks/bench_eval.py CHECKPOINT --exit 4 --episodes 16
    .venv/bin/python benchmarks/bench_eval.py --quick          # tiny untrained checkpoint

(a) `so101-sim eval` on N episodes with K env workers: wall time and the physics / render /
policy split (target: the shipped policy's 200 seeds in <= 100 s on 2 cores). It renders the
harness's default way (the smallest size that passes the self-check against the training
data's size, then resize_frames) unless --image-size is given. It also prints the cores'
busy time over the run (/proc/stat) and the wall that work needs at the least, spread
perfectly over the cores: a target below that floor needs less work, not better scheduling;
and one digest of all its episodes' actions, to tell later runs whether they made the same ones.
(b) with --compare-lerobot, the same checkpoint and seeds through `lerobot-eval
--env.type=so101_pick_place` and through the harness, both rendering at the policy's input
size (lerobot-eval cannot resize) and both writing 10 videos (lerobot-eval always does):
wall time of each whole command, the speed-up (target >= 4x) and whether the success rates'
95% intervals overlap, and the highest speed-up the harness's measured work allows against
that lerobot-eval wall (its floor, as in (a)). `--precision bf16` runs (b) with bfloat16
autocast in both tools (the harness's `--precision bf16`, lerobot-eval's
`--policy.use_amp=true`), so both do the same arithmetic; fp32 (the default) is both
tools' default.
(c) with --paths, run (a) against --faithful on the same seeds, side by side: wall time of
each, the ratio, and `so101-sim compare` on the pair (both rates, the discordant seeds, exact
McNemar p). (d) with --bf16, run (a) against the same with `--precision bf16`, likewise.
(e) with --plain-kernels, run (a) against the same with the harness's exact forward speed-ups
undone (torch's own max-pooling kernel instead of harness.policies.pooling's channels-last
one, glibc's default heap instead of utils.heap's, the eager U-Net instead of
harness.policies.traced's graph, the image encoder always whole on the forward's thread),
likewise, and count the episodes whose actions differ (their digests): there should be none.
(f) with --startup R, only this: R rounds of `so101-sim eval` as shipped against the same
command with its start-up speed-ups undone (no early fork server from harness.warmup, and
the collector left as it is: main() called as a library, so utils.collector does nothing),
alternating, on the same seeds: each wall, the medians, their ratio, and the episodes whose
actions differ (none expected: only start-up and exit change).
(g) with --tail R, only this: R rounds as shipped against the same command with the
forward scheduling of before commit 537fdba (a short batch waited for the forward in flight
instead of taking the free forward thread, and a second forward thread only with twice the
rows of one forward in envs), alternating, likewise. Exact too: every row is padded to the
same batch on one thread either way.
(h) with --trace R, only this: R rounds as shipped against the same command with the diffusion
U-Net run eagerly instead of as harness.policies.traced's recorded graph, alternating,
likewise. Exact: the graph calls the same ATen operations.
(i) with --split R, only this: R rounds as shipped against the same command with the image
encoder always run whole on the forward's own thread instead of in two halves on two cores
when a core is free (harness.policies.encoder_split), alternating, likewise. Exact: the halves
are used only where a load-time check found them bitwise equal to the whole batch.
(j) with --exit R, only this: R rounds as shipped against the same command whose fork server
tears its interpreter down when the command exits instead of leaving at once
(workers.server_init), alternating, likewise. Exact: only the exit changes.
Without a checkpoint a tiny untrained DiffusionPolicy is built (tests/tiny_policy.py): it fails
every episode, so only the timings mean anything.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from so101_sim.cli import parse_image_size

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
#: The cores this process (and the commands it runs) may use: what a run's work spreads over.
CORES = len(os.sched_getaffinity(0))


def short_task(out_dir: Path, max_steps: int) -> Path:
    """pick_place with episodes cut to `max_steps` (for --quick)."""
    from so101_sim.utils.paths import envs_dir

    text = re.sub(r"(?m)^max_steps\s*=\s*\d+", f"max_steps = {max_steps}",
                  (envs_dir() / "pick_place.toml").read_text())
    path = out_dir / f"pick_place_{max_steps}.toml"
    path.write_text(text)
    return path


def policy_input_size(ckpt: Path) -> tuple[int, int]:
    cfg = json.loads((ckpt / "config.json").read_text())
    shapes = [f["shape"] for k, f in cfg["input_features"].items()
              if k.startswith("observation.images.")]
    return int(shapes[0][1]), int(shapes[0][2])


#: `so101-sim` with the exact speed-ups undone before the policy module is imported, for (e).
PLAIN_KERNELS = (
    "import sys; import so101_sim.harness.policies.pooling as p; import so101_sim.utils.heap as h; "
    "import so101_sim.harness.policies.traced as t; t.use_traced_unet = lambda m, log=None: 0; "
    "import so101_sim.harness.policies.encoder_split as e; "
    "e.use_split_encoder = lambda m, spare=None: 0; "
    "p.use_channels_last_pooling = lambda module: 0; h.keep_freed_memory = lambda log=None: False; "
    "from so101_sim.cli import main; sys.argv[0] = 'so101-sim'; sys.exit(main())")


#: `so101-sim` with the diffusion U-Net run eagerly (no traced graph), for (h).
PLAIN_TRACE = (
    "import sys; import so101_sim.harness.policies.traced as t; "
    "t.use_traced_unet = lambda m, log=None: 0; "
    "from so101_sim.cli import main; sys.argv[0] = 'so101-sim'; sys.exit(main())")


#: `so101-sim` with the image encoder always whole on the forward's thread, for (i).
PLAIN_SPLIT = (
    "import sys; import so101_sim.harness.policies.encoder_split as e; "
    "e.use_split_encoder = lambda m, spare=None: 0; "
    "from so101_sim.cli import main; sys.argv[0] = 'so101-sim'; sys.exit(main())")


#: `so101-sim` without its start-up speed-ups, for (f): no early fork server, and main()
#: called with its arguments as a library would, so it does not own the process's collector.
PLAIN_STARTUP = (
    "import sys; import so101_sim.harness.warmup as w; w.warm_eval_workers = lambda **k: False; "
    "from so101_sim.cli import main; sys.exit(main(sys.argv[1:]))")


#: `so101-sim` with the forward scheduling of before commit 537fdba, for (g).
PLAIN_TAIL = (
    "import sys; from so101_sim.harness.forwards import Forwards as F; "
    "F.pair_helps = staticmethod(lambda envs, batch: envs >= 2 * batch); "
    "F.should_launch = lambda self, waiting, batch, envs_stepping: bool(waiting) and "
    "self.can_launch() and (waiting >= batch or (not envs_stepping and not self.inflight)); "
    "from so101_sim.cli import main; sys.argv[0] = 'so101-sim'; sys.exit(main())")

#: `so101-sim` whose fork server tears its interpreter down at exit (no workers.server_init
#: among its preloads), for (j).
PLAIN_EXIT = (
    "import sys; import so101_sim.workers.local as l; "
    "l.server_preload = lambda preload: list(preload); "
    "from so101_sim.cli import main; sys.argv[0] = 'so101-sim'; sys.exit(main())")

#: The script of each undone variant: (e) kernels, (f) startup, (g) tail, (h) trace,
#: (i) split, (j) exit.
PLAIN = {"kernels": PLAIN_KERNELS, "startup": PLAIN_STARTUP, "tail": PLAIN_TAIL,
         "trace": PLAIN_TRACE, "split": PLAIN_SPLIT, "exit": PLAIN_EXIT}


#: The alternating A/B runs, by flag: (label, name of the undone variant in the table, what
#: the undone variant does, for --help). Their scripts are PLAIN[kind].
AB_KINDS = {
    "startup": ("f", "start-up undone", "the start-up speed-ups undone"),
    "tail": ("g", "scheduling undone", "the forward scheduling of before"),
    "trace": ("h", "eager U-Net", "the diffusion U-Net run eagerly instead of as a traced "
                                  "graph"),
    "split": ("i", "encoder whole", "the image encoder never split over two cores"),
    "exit": ("j", "server teardown", "the fork server's interpreter teardown at exit (no "
                                     "workers.server_init)"),
}


def run_harness(ckpt: Path, out: Path, episodes: int, n_envs: int, videos: int,
                image_size: tuple[int, int] | None, task: str,
                flags: tuple[str, ...] = (), plain: bool | str = False) -> tuple[float, dict]:
    exe = ([sys.executable, "-c", PLAIN["kernels" if plain is True else plain]] if plain
           else [str(BIN / "so101-sim")])
    cmd = [*exe, "eval", "--policy", str(ckpt), "--task", task,
           "--episodes", str(episodes), "--n-envs", str(n_envs), "--videos", str(videos),
           "--out", str(out), *flags]
    if image_size:
        cmd += ["--image-size", f"{image_size[0]}x{image_size[1]}"]
    wall = timed(cmd)
    return wall, json.loads((out / "eval_info.json").read_text())["aggregated"]


def run_lerobot_eval(ckpt: Path, out: Path, episodes: int, n_envs: int,
                     image_size: tuple[int, int], task: str, episode_length: int,
                     amp: bool = False) -> tuple:
    cmd = [str(BIN / "lerobot-eval"), f"--policy.path={ckpt}", "--policy.device=cpu",
           "--env.type=so101_pick_place", "--env.discover_packages_path=so101_sim.lerobot_plugin",
           f"--env.task={task}", f"--env.episode_length={episode_length}",
           f"--env.image_height={image_size[0]}", f"--env.image_width={image_size[1]}",
           f"--eval.n_episodes={episodes}", f"--eval.batch_size={n_envs}",
           "--seed=100000", f"--output_dir={out}", f"--policy.use_amp={str(amp).lower()}"]
    wall = timed(cmd)
    info = json.loads((out / "eval_info.json").read_text())
    agg = info.get("overall", info.get("aggregated"))
    return wall, agg


def timed(cmd: list[str]) -> float:
    """Wall time of a whole command (imports and loading included); its output is shown
    only if it fails."""
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        sys.exit(f"{Path(cmd[0]).name} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return time.perf_counter() - t0


def rate(k: float, n: int) -> str:
    from so101_sim.harness.stats import wilson_interval

    lo, hi = wilson_interval(round(k), n)
    return f"{round(k)}/{n} = {100 * k / n:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", nargs="?", help="lerobot checkpoint dir (default: tiny)")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--n-envs", type=int, default=16,
                        help="env workers (default 16, as `so101-sim eval`)")
    parser.add_argument("--image-size", default=None, help="HxW for (a); default: harness's")
    parser.add_argument("--compare-lerobot", action="store_true", help="also run (b)")
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                        help="(b)'s forwards in both tools: fp32, or bfloat16 autocast in both")
    parser.add_argument("--paths", action="store_true",
                        help="run (c): the default render path against --faithful")
    parser.add_argument("--plain-kernels", action="store_true",
                        help="(e): also run (a) without the exact speed-ups, same seeds")
    for kind, (label, _, undone_help) in AB_KINDS.items():
        parser.add_argument(f"--{kind}", type=int, default=0, metavar="R",
                            help=f"only ({label}): R alternating rounds, as shipped and "
                                 f"with {undone_help}")
    parser.add_argument("--bf16", action="store_true",
                        help="run (d): fp32 forwards against --precision bf16")
    parser.add_argument("--quick", action="store_true",
                        help="4 episodes of 48 steps, 2 envs, (a) and (b): a sanity run")
    parser.add_argument("--max-steps", type=int, default=None,
                        help="cut episodes to this many steps (a shorter task file)")
    parser.add_argument("--out", default=None, help="folder for the runs (default: a temp dir)")
    args = parser.parse_args()
    rounds = {kind: getattr(args, kind) for kind in AB_KINDS}
    if sum(bool(r) for r in rounds.values()) > 1:
        parser.error(", ".join(f"--{kind}" for kind in AB_KINDS)
                     + " each run their own rounds; give one")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    # Both commands run with the caller's OpenMP settings (libgomp's default unless set): the
    # harness sets none itself, and neither does lerobot-eval.

    work = Path(args.out or tempfile.mkdtemp(prefix="bench_eval_"))
    work.mkdir(parents=True, exist_ok=True)
    task, episode_length = "pick_place", 300
    if args.quick:
        args.episodes, args.n_envs, args.compare_lerobot = 4, 2, True
        args.max_steps = args.max_steps or 48
    if args.max_steps:
        episode_length = args.max_steps
        task = str(short_task(work, episode_length))
    if args.checkpoint:
        ckpt = Path(args.checkpoint)
    else:
        sys.path.insert(0, str(ROOT / "tests"))
        from tiny_policy import make_tiny_diffusion_checkpoint

        ckpt = make_tiny_diffusion_checkpoint(work / "tiny_ckpt", input_size=(48, 64),
                                              dataset_image_size=(96, 128))
        print(f"no checkpoint given: built a tiny untrained DiffusionPolicy in {ckpt}")
    size = parse_image_size(args.image_size) if args.image_size else None

    n, k = args.episodes, args.n_envs
    for kind, r in rounds.items():
        if r:
            ab_rounds(r, kind, ckpt, work, n, k, task)
            return
    busy0 = busy_core_s()
    wall, agg = run_harness(ckpt, work / "harness_a", n, k, 2, size, task)
    busy = busy_core_s() - busy0
    t = agg["time"]
    print(f"(a) harness, {n} episodes, {k} envs: wall {wall:.1f} s ({wall / n:.2f} s/episode, "
          f"eval loop {agg['eval_s']:.1f} s); physics {t['physics_s']:.1f} s, render "
          f"{t['render_s']:.1f} s, policy {t['policy_s']:.1f} s (summed over episodes); "
          f"success {rate(agg['n_success'], n)}"
          + ("  [target: 200 episodes <= 100 s]" if not args.quick else ""))
    info = json.loads((work / "harness_a" / "eval_info.json").read_text())
    first = min(e["seconds"] for e in info["per_episode"])
    print(f"    start-up: {wall - agg['eval_s']:.1f} s before the loop (imports, checkpoint, "
          f"render self-check), workers up in {info['config']['workers']['start_s']:.1f} s, "
          f"first episode done {first:.1f} s after its reset ({k} envs start together)")
    print(f"    {floor_line(busy, wall)}")
    print(f"    actions digest {run_digest(info['per_episode'])} (same digest, same rollouts)")
    if args.paths:
        compare_variant("(c)", "faithful", wall, ckpt, work, n, k, task, ("--faithful",))
    if args.bf16:
        compare_variant("(d)", "bf16", wall, ckpt, work, n, k, task, ("--precision", "bf16"))
    if args.plain_kernels:
        compare_variant("(e)", "plain", wall, ckpt, work, n, k, task, (), plain=True)
    if not args.compare_lerobot:
        return
    inp = policy_input_size(ckpt)
    bf16 = args.precision == "bf16"
    busy0 = busy_core_s()
    w_h, a_h = run_harness(ckpt, work / "harness_b", n, k, min(10, n), inp, task,
                           ("--precision", args.precision))
    busy_h = busy_core_s() - busy0
    w_l, a_l = run_lerobot_eval(ckpt, work / "lerobot_b", n, k, inp, task, episode_length,
                                amp=bf16)
    k_h, k_l = a_h["n_success"], a_l["pc_success"] * n / 100
    from so101_sim.harness.stats import wilson_interval

    lo_h, hi_h = wilson_interval(round(k_h), n)
    lo_l, hi_l = wilson_interval(round(k_l), n)
    overlap = lo_h <= hi_l and lo_l <= hi_h
    print(f"(b) same checkpoint and seeds 100000.., {inp[0]}x{inp[1]} renders, {k} envs, "
          f"{min(10, n)} videos each, "
          f"{'bf16 autocast in both' if bf16 else 'fp32 in both'}:")
    for name, wall, k_x, agg in (("harness", w_h, k_h, a_h), ("lerobot-eval", w_l, k_l, a_l)):
        print(f"    {name:12s} {wall:7.1f} s  success {rate(k_x, n)}  "
              f"(its loop {agg['eval_s']:.1f} s)")
    print(f"    speed-up {w_l / w_h:.2f}x (target >= 4x); 95% intervals "
          f"{'overlap' if overlap else 'DO NOT overlap'}")
    need = 4 * busy_h / (w_l * CORES)
    print(f"    harness: {floor_line(busy_h, w_h)}, so at most {w_l * CORES / busy_h:.2f}x "
          f"against this lerobot-eval run; 4x needs "
          + ("no less work" if need <= 1 else f"{100 * (1 - 1 / need):.0f}% less work"))


def run_digest(per_episode: list[dict]) -> str:
    """Every episode's action digest in seed order, hashed: compares runs whose folders are gone."""
    ordered = sorted(per_episode, key=lambda e: e["seed"])
    lines = (f"{e['seed']}:{e['actions_sha']}" for e in ordered)
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()[:16]


def floor_line(busy: float, wall: float) -> str:
    """The shortest wall a run's work allows: its busy core-seconds spread perfectly over
    the cores this process may use. A target below it needs less work, not better scheduling."""
    return (f"cores busy {busy:.1f} core-s over the {wall:.1f} s; that work takes at least "
            f"{busy / CORES:.1f} s on {CORES} cores however it is scheduled")


def compare_variant(label: str, name: str, wall_a: float, ckpt: Path, work: Path, n: int,
                    k: int, task: str, flags: tuple[str, ...], plain: bool = False) -> None:
    """Run (a)'s seeds again with `flags`; both walls, the ratio and the paired comparison."""
    wall, agg = run_harness(ckpt, work / f"variant_{name}", n, k, 2, None, task, flags, plain)
    a = json.loads((work / "harness_a" / "eval_info.json").read_text())["aggregated"]
    what = "the exact speed-ups undone" if plain else " ".join(flags)
    print(f"{label} {n} episodes, {k} envs, the same seeds, (a) against {what}:")
    print(f"    default {wall_a:7.1f} s  success {rate(a['n_success'], n)}")
    print(f"    {name:7s} {wall:7.1f} s  success {rate(agg['n_success'], n)}")
    print(f"    {name} / default wall: {wall / wall_a:.2f}x")
    from so101_sim.harness.compare import compare_runs, summary_lines

    for line in summary_lines(compare_runs(work / "harness_a", work / f"variant_{name}")):
        print(f"    {line}")
    digests = [{e["seed"]: e["actions_sha"] for e in json.loads(
        (work / run / "eval_info.json").read_text())["per_episode"]}
        for run in ("harness_a", f"variant_{name}")]
    differ = sum(digests[0][s] != digests[1].get(s) for s in digests[0])
    print(f"    episodes whose actions differ (digests): {differ} of {len(digests[0])}")


def ab_rounds(rounds: int, kind: str, ckpt: Path, work: Path, n: int, k: int,
              task: str) -> None:
    """(f) to (j): `rounds` alternating pairs, as shipped and with `kind`'s speed-up
    undone."""
    import statistics

    label, undone, _ = AB_KINDS[kind]
    walls: dict[str, list[float]] = {"as shipped": [], undone: []}
    digests: dict[str, set[str]] = {name: set() for name in walls}
    idles: dict[str, list[float]] = {name: [] for name in walls}
    for r in range(rounds):
        for name, plain in ((undone, kind), ("as shipped", False)):
            out = work / f"{kind}_{'plain' if plain else 'shipped'}_{r}"
            idle0 = idle_core_s()
            wall, agg = run_harness(ckpt, out, n, k, 2, None, task, plain=plain)
            idle = idle_core_s() - idle0
            walls[name].append(wall)
            idles[name].append(idle)
            per = json.loads((out / "eval_info.json").read_text())["per_episode"]
            digests[name].add(json.dumps(sorted((e["seed"], e["actions_sha"]) for e in per)))
            print(f"    round {r + 1}: {name:17s} {wall:6.1f} s (loop {agg['eval_s']:.1f} s), "
                  f"success {agg['n_success']}/{n}, cores idle {idle:.1f} core-s", flush=True)
    med = {name: statistics.median(w) for name, w in walls.items()}
    idle_med = {name: statistics.median(w) for name, w in idles.items()}
    print(f"({label}) {n} episodes, {k} envs, {rounds} alternating rounds: as shipped "
          f"{med['as shipped']:.1f} s against {med[undone]:.1f} s "
          f"({undone}; medians), {med[undone] / med['as shipped']:.2f}x; the same "
          f"actions in every run: {len(digests['as shipped'] | digests[undone]) == 1}; "
          f"cores idle {idle_med['as shipped']:.1f} against {idle_med[undone]:.1f} core-s")


def busy_core_s() -> float:
    """User, system and interrupt time of all cores so far, from /proc/stat: the work done
    while a run ran (the run's own, if nothing else runs), not counting time stolen by the
    hypervisor."""
    f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:8]]
    return (f[0] + f[1] + f[2] + f[5] + f[6]) / os.sysconf("SC_CLK_TCK")


def idle_core_s() -> float:
    """Idle (and I/O wait) time of all cores so far, from /proc/stat: what a run leaves
    unused shows up here whatever the machine's speed that minute."""
    fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    return (int(fields[4]) + int(fields[5])) / os.sysconf("SC_CLK_TCK")


if __name__ == "__main__":
    main()
