"""How fast `so101-sim eval --against RUN` calls a regression, and a non-regression.

    .venv/bin/python benchmarks/bench_against.py policy/pick_place_diffusion \
        [--noise 0.014] [--repeats 1] [--windows 4] [--reference RUN] [--out DIR]

The weakened checkpoint is the given one with seeded Gaussian noise added to every weight of
its denoising U-Net (vision encoder untouched): each tensor gets noise of `--noise` times its
own RMS (seed 0). The defaults measure the target's case: noise 0.014 costs the shipped
policy 10.6 points pooled over 1000 seeds (benchmarks/README.md), and five windows give the
median wall. Steps, all with the harness defaults (render path, 16 envs), seeds 100000..:

1. the reference: the checkpoint on 200 seeds (skipped when --reference names such a run);
2. the weakened checkpoint on the same 200 seeds, paired with `so101-sim compare`: its real
   drop in points and McNemar p, so "a 10-point regression" is measured, not assumed;
3. `eval --policy WEAK --against REF` and `eval --policy CKPT --against REF`, `--repeats` times
   each: wall time of the whole command, episodes used and the verdict (target: "worse" in
   <= 60 s median, "not worse" in about the same);
4. the same test replayed offline over 2000 random orders of the 200 measured pairs: the
   median and 90th percentile of episodes used, so one lucky seed order does not decide;
5. with `--windows K`: K more windows of 200 seeds after the reference's (100200..,
   100400.., ...), each with its own reference run of CHECKPOINT and full run of the weakened
   one (kept in --out and reused for the same weights) and one `--against` run of each
   policy: the median wall over the windows is measured, not inferred from one seed order,
   and the weakened checkpoint's drop is pooled over all seeds (one window's 200 seeds put it
   within about +-6 points), with the test replayed on random 200-seed draws from the pooled
   pairs.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BIN = Path(sys.executable).parent


def weaken(ckpt: Path, out: Path, noise: float, seed: int = 0) -> Path:
    """A copy of `ckpt` whose U-Net weights carry noise of `noise` x each tensor's RMS."""
    import torch
    from safetensors.torch import load_file, save_file

    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(ckpt, out)
    weights = load_file(str(ckpt / "model.safetensors"))
    gen = torch.Generator().manual_seed(seed)
    for name in sorted(weights):
        tensor = weights[name]
        if ".unet." not in f".{name}" or not tensor.is_floating_point():
            continue
        full = tensor.float()
        rms = full.pow(2).mean().sqrt()
        weights[name] = (full + noise * rms * torch.randn(full.shape, generator=gen)
                         ).to(tensor.dtype)
    save_file(weights, str(out / "model.safetensors"))
    return out


def run(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        sys.exit(f"{Path(cmd[0]).name} {cmd[1]} failed ({proc.returncode}):\n"
                 f"{proc.stderr[-3000:]}")
    return time.perf_counter() - t0


@functools.cache  # each kept folder asks: a checkpoint's weights are read once per call
def weights_of(policy: Path) -> str:
    """The digest `so101-sim eval` records as a run's policy_weights."""
    from so101_sim.harness.policies.checks import weights_digest

    return weights_digest(policy / "model.safetensors")


def finished(folder: Path, policy: Path) -> bool:
    """Whether `folder` holds a finished run of `policy`'s weights, kept from an earlier call
    and reused. A run of other weights there (another --noise or checkpoint into the same
    --out) is refused: pairing it would mix two policies without a word."""
    info = folder / "eval_info.json"
    if not info.exists():
        return False
    ran = json.loads(info.read_text(encoding="utf-8")).get("config", {}).get("policy_weights")
    if ran != (want := weights_of(policy)):
        sys.exit(f"{folder} holds a run of weights {ran}, not {policy}'s ({want}): another "
                 "--noise or checkpoint was run into this --out before; choose a new --out "
                 "(and pass --reference to reuse a reference run of the same checkpoint)")
    return True


def eval_cmd(policy: Path, out: Path, *extra: str) -> list[str]:
    return [str(BIN / "so101-sim"), "eval", "--policy", str(policy), "--task", "pick_place",
            "--videos", "0", "--out", str(out), *extra]


def outcomes(run_dir: Path) -> dict[int, bool]:
    from so101_sim.harness.compare import load_run

    return dict(load_run(run_dir).success)


def paired(ref: dict[int, bool], new: dict[int, bool]) -> tuple[np.ndarray, np.ndarray]:
    """Both runs' outcomes (0/1) on the seeds they share, in seed order."""
    seeds = sorted(set(ref) & set(new))
    return (np.array([ref[s] for s in seeds], dtype=np.int64),
            np.array([new[s] for s in seeds], dtype=np.int64))


def replay_orders(ref: dict[int, bool], new: dict[int, bool], orders: int,
                  margin: float, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Verdicts and episodes used by the sequential test on random orders of the measured
    pairs (the same permutation applied to both runs, so the pairs stay pairs)."""
    from so101_sim.harness.sequential import batch_verdicts

    a, b = paired(ref, new)
    rng = np.random.default_rng(0)
    perms = np.stack([rng.permutation(len(a)) for _ in range(orders)])
    return batch_verdicts(a[perms], b[perms], margin=margin, alpha=alpha)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--noise", type=float, default=0.014,
                        help="U-Net weight noise, as a fraction of each tensor's RMS (default "
                        "0.014: a 10-point regression of the shipped pick_place policy)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="--against runs of each policy on the first window")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--reference", default=None,
                        help="an earlier 200-seed run of CHECKPOINT (default: run it)")
    parser.add_argument("--out", default=None)
    parser.add_argument("--windows", type=int, default=4,
                        help="more 200-seed windows to run step 3 on (see step 5; 0 for none)")
    args = parser.parse_args()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    work = Path(args.out or tempfile.mkdtemp(prefix="bench_against_"))
    work.mkdir(parents=True, exist_ok=True)
    ckpt = Path(args.checkpoint)
    n = str(args.episodes)

    ref = Path(args.reference) if args.reference else work / "reference"
    if not finished(ref, ckpt):
        wall = run(eval_cmd(ckpt, ref, "--episodes", n))
        print(f"1. reference: {ckpt} on {n} seeds in {wall:.1f} s")
    weak = weaken(ckpt, work / f"weak_noise{args.noise:g}", args.noise)
    weak_full = work / "weak_full"
    if not finished(weak_full, weak):
        run(eval_cmd(weak, weak_full, "--episodes", n))
    from so101_sim.harness.compare import compare_runs, summary_lines

    print(f"2. weakened checkpoint (U-Net weights + {args.noise:g} x RMS noise, seed 0) on the "
          "same seeds:")
    for line in summary_lines(compare_runs(ref, weak_full)):
        print(f"    {line}")

    rows = {}
    for name, policy in (("weakened", weak), ("itself", ckpt)):
        walls, used, verdicts = [], [], []
        for i in range(args.repeats):
            out = work / f"against_{name}_{i}"
            shutil.rmtree(out, ignore_errors=True)
            walls.append(run(eval_cmd(policy, out, "--against", str(ref))))
            v = json.loads((out / "eval_info.json").read_text())["sequential_verdict"]
            used.append(v["episodes"])
            verdicts.append(v["verdict"])
        rows[name] = (walls, used, verdicts)
        print(f"3. --against, {name}: verdict {sorted(set(verdicts))}, episodes {used}, wall "
              f"{', '.join(f'{w:.1f}' for w in walls)} s, median {statistics.median(walls):.1f} s"
              + ("  [target: worse in <= 60 s]" if name == "weakened" else ""))

    ref_out, weak_out = outcomes(ref), outcomes(weak_full)
    for name, new in (("weakened", weak_out), ("itself", ref_out)):
        verdicts, used = replay_orders(ref_out, new, 2000, margin=0.0, alpha=0.05)
        counts = {v: int((verdicts == v).sum()) for v in sorted(set(verdicts.tolist()))}
        print(f"4. 2000 random orders of the 200 pairs, {name}: verdicts {counts}; episodes "
              f"used median {int(np.median(used))}, p90 {int(np.percentile(used, 90))}")
    if args.windows > 0:
        other_windows(work, ckpt, weak, args.windows, int(n), rows, (ref_out, weak_out))


def pooled_draws(ref: dict[int, bool], new: dict[int, bool], n: int, draws: int = 4000) -> str:
    """The test on `draws` random `n`-seed draws from all the pooled pairs: what a window of
    `n` seeds does on average, without one window's luck."""
    from so101_sim.harness.sequential import batch_verdicts

    a, b = paired(ref, new)
    rng = np.random.default_rng(0)
    picks = np.stack([rng.choice(len(a), n, replace=False) for _ in range(draws)])
    verdicts, used = batch_verdicts(a[picks], b[picks], margin=0.0, alpha=0.05)
    counts = {v: int((verdicts == v).sum()) for v in sorted(set(verdicts.tolist()))}
    p25, p50, p75 = (int(np.percentile(used, q)) for q in (25, 50, 75))
    return (f"{draws} random {n}-seed draws from the {len(a)} pooled pairs, weakened: "
            f"verdicts {counts}; episodes used median {p50} (p25 {p25}, p75 {p75})")


def other_windows(work: Path, ckpt: Path, weak: Path, windows: int, n: int,
                  rows: dict[str, tuple[list, list, list]],
                  first: tuple[dict[int, bool], dict[int, bool]]) -> None:
    """Step 5: step 3 once per further window of `n` seeds (the medians include step 3's), and
    the weakened checkpoint's full run of each window, so its drop is pooled over all."""
    from so101_sim.harness.stats import mcnemar_p_value, paired_difference_interval

    walls = {name: [statistics.median(rows[name][0])] for name in rows}
    verdicts = {name: [rows[name][2][0]] for name in rows}
    ref_all, weak_all = dict(first[0]), dict(first[1])
    after = max(ref_all) + 1  # windows follow the reference's seeds, whatever its start
    for k in range(1, windows + 1):
        start = str(after + (k - 1) * n)
        ref, weak_full = work / f"reference_{start}", work / f"weak_full_{start}"
        for policy, folder in ((ckpt, ref), (weak, weak_full)):
            if not finished(folder, policy):
                run(eval_cmd(policy, folder, "--episodes", str(n), "--seed-start", start))
        ref_all.update(outcomes(ref))
        weak_all.update(outcomes(weak_full))
        cells = []
        for name, policy in (("weakened", weak), ("itself", ckpt)):
            out = work / f"against_{name}_{start}"
            shutil.rmtree(out, ignore_errors=True)
            wall = run(eval_cmd(policy, out, "--against", str(ref)))
            v = json.loads((out / "eval_info.json").read_text())["sequential_verdict"]
            walls[name].append(wall)
            verdicts[name].append(v["verdict"])
            cells.append(f"{name} {v['verdict']} after {v['episodes']} in {wall:.1f} s")
        print(f"5. seeds {start}..{int(start) + n - 1}: " + "; ".join(cells))
    a, b = paired(ref_all, weak_all)
    both = int((a & b).sum())
    only_a, only_b = int(a.sum()) - both, int(b.sum()) - both
    lo, hi = paired_difference_interval(both, only_a, only_b, len(a) - both - only_a - only_b)
    print(f"5. pooled over {len(a)} seeds: reference {a.sum()}, weakened {b.sum()}: "
          f"{100 * (a.sum() - b.sum()) / len(a):+.1f} points ({100 * lo:+.1f} to "
          f"{100 * hi:+.1f}), McNemar p = {mcnemar_p_value(only_a, only_b):.2g}")
    print("5. " + pooled_draws(ref_all, weak_all, n))
    for name in walls:
        counts = {v: verdicts[name].count(v) for v in sorted(set(verdicts[name]))}
        print(f"5. {len(walls[name])} windows, {name}: verdicts {counts}; wall median "
              f"{statistics.median(walls[name]):.1f} s ("
              f"{', '.join(f'{w:.1f}' for w in walls[name])})"
              + ("  [target: worse in <= 60 s median]" if name == "weakened" else ""))


if __name__ == "__main__":
    main()
