"""Training throughput: `so101-sim train` vs `lerobot-train`, same dataset and preset, one run.

Both train the same DiffusionPolicy (the preset's fields; for lerobot-train the resize to the
preset's image size is done inside the policy with `resize_shape`, and the crop ratio gives the
same crop) on the same dataset for the same number of steps, one after the other. Throughput is
taken from the steady state (ours: the time between logged steps; lerobot-train: a long run
minus a short one), so start-up, the one-off frame-cache build and checkpoint writing are
excluded; the wall time including start-up is printed too. The ratio compares fp32 with
fp32; a third row shows this trainer with --precision bf16 (wall there excludes the frame
cache, which it reuses).

    .venv/bin/python benchmarks/bench_train.py --dataset ~/so101-runs/data/pp200 --steps 30
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from so101_sim.train.presets import load_preset  # noqa: E402

WARMUP_STEPS = 2  # this trainer's first logged steps, left out of its rate

# DiffusionConfig fields passed to lerobot-train as --policy.<field>=<value>.
_SKIP = {"normalization_mapping", "resize_shape", "crop_shape", "crop_ratio", "device",
         "push_to_hub"}


def _cli_value(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, tuple | list):
        return "[" + ",".join(str(x) for x in v) + "]"
    return str(v).lower() if isinstance(v, bool) else str(v)


def run_ours(dataset: Path, preset: str, steps: int, batch: int, work: Path,
             precision: str = "fp32") -> dict:
    out = work / f"ours_{precision}"
    if precision != "fp32":  # reuse the fp32 run's decoded frames
        out.mkdir()
        (out / "frame_cache").symlink_to(work / "ours_fp32" / "frame_cache")
    code = ("import sys, json; from pathlib import Path; from so101_sim.train import train; "
            f"r = train(Path({str(dataset)!r}), Path({str(out)!r}), preset_name={preset!r}, "
            f"steps={steps}, batch_size={batch}, progress=False, log_every=1, "
            f"precision={precision!r}, keep_frame_cache=True)")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, text=True,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    total = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"so101-sim train ({precision}) failed:\n{proc.stderr[-4000:]}")
    rows = [json.loads(x) for x in (out / "train_log.jsonl").read_text().splitlines()]
    warm = rows[WARMUP_STEPS:]  # allocator and thread-pool warm-up
    span = warm[-1]["wall_s"] - warm[0]["wall_s"]
    per_step = span / (warm[-1]["step"] - warm[0]["step"])
    return {"samples_per_s": batch / per_step, "s_per_step": per_step, "total_s": total}


def run_lerobot(dataset: Path, preset_name: str, steps: int, batch: int, work: Path,
                workers: int) -> dict:
    preset = load_preset(preset_name)
    d = preset.policy
    args = [str(Path(sys.executable).parent / "lerobot-train"),
            f"--dataset.repo_id=local/{dataset.name}", f"--dataset.root={dataset}",
            "--policy.type=diffusion", "--policy.device=cpu", "--policy.push_to_hub=false",
            f"--policy.resize_shape=[{preset.image_size[0]},{preset.image_size[1]}]",
            f"--policy.crop_ratio={d['crop_shape'][0] / preset.image_size[0]}",
            f"--steps={steps}", f"--batch_size={batch}",
            f"--num_workers={workers}", "--log_freq=1", "--save_checkpoint=false",
            "--wandb.enable=false",
            f"--dataset.use_imagenet_stats={str(preset.image_normalize == 'imagenet').lower()}"]
    for k, v in d.items():
        if k not in _SKIP:
            args.append(f"--policy.{k}={_cli_value(v)}")
    # lerobot-train logs no per-step timing we can read, so time a short and a long run:
    # the difference is `steps` steady-state steps, start-up cancels out.
    walls = []
    for n in (5, 5 + steps):
        run = [a for a in args if not a.startswith(("--steps=", "--output_dir="))]
        run += [f"--steps={n}", f"--output_dir={work / f'lerobot_{n}'}"]
        t0 = time.perf_counter()
        proc = subprocess.run(run, capture_output=True, text=True, cwd=work,
                              env={**os.environ, "HF_HUB_OFFLINE": "1"})
        walls.append(time.perf_counter() - t0)
        if proc.returncode != 0:
            raise SystemExit(f"lerobot-train failed:\n{proc.stderr[-4000:]}")
    total = walls[1]
    per_step = (walls[1] - walls[0]) / steps
    return {"samples_per_s": batch / per_step, "s_per_step": per_step, "total_s": total}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, required=True)
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--batch-size", type=int, default=None)
    ap.add_argument("--lerobot-workers", type=int, default=2,
                    help="lerobot-train DataLoader workers (video decoding); 2 = the cores")
    a = ap.parse_args()
    if a.steps < WARMUP_STEPS + 2:
        ap.error(f"--steps {a.steps} is too few: the first {WARMUP_STEPS} are warm-up and the "
                 f"rate is read between the steps after them; give --steps {WARMUP_STEPS + 2} "
                 "or more (default 30)")
    batch = a.batch_size or load_preset(a.preset).train.batch_size
    with tempfile.TemporaryDirectory(prefix="bench_train_") as tmp:
        work = Path(tmp)
        ours = run_ours(a.dataset.expanduser(), a.preset, a.steps, batch, work)
        bf16 = run_ours(a.dataset.expanduser(), a.preset, a.steps, batch, work, "bf16")
        theirs = run_lerobot(a.dataset.expanduser(), a.preset, a.steps, batch, work,
                             a.lerobot_workers)
    print(f"preset {a.preset}, batch {batch}, {a.steps} steps, dataset {a.dataset}, "
          f"torch threads {os.cpu_count()}, load avg {os.getloadavg()[0]:.2f}")
    print("| trainer | samples/s | s/step | wall incl. start-up |")
    print("|---|---|---|---|")
    for name, r in (("so101-sim train (fp32)", ours), ("lerobot-train (fp32)", theirs),
                    ("so101-sim train --precision bf16", bf16)):
        print(f"| {name} | {r['samples_per_s']:.1f} | {r['s_per_step']:.2f} | "
              f"{r['total_s']:.0f} s |")
    print(f"ratio (samples/s), both fp32: {ours['samples_per_s'] / theirs['samples_per_s']:.2f}x"
          f"; with --precision bf16: {bf16['samples_per_s'] / theirs['samples_per_s']:.2f}x")


if __name__ == "__main__":
    main()
