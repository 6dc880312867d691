"""Per-step training speed of a preset under settings that do not change what is learnt.

    .venv/bin/python benchmarks/bench_train_step.py [--preset cpu] [--steps 20]

Each variant runs in its own child process (fresh torch, same seed, same synthetic batch shapes
as `so101-sim train` feeds the policy) one after another in this one run, so the ratios compare
like with like: fp32, bf16 autocast, bf16 + channels_last memory format, bf16 + torch.compile
(inductor on CPU; compile time is reported apart from the steady state), 1 vs all threads, and
the batch in 2 parts of one thread each (`so101_sim.train.threads.BatchParts`, what `train`
does beside a busy neighbour). `--busy` times every variant beside one spinning process too.
A preset with an ``[augment]`` section (cpu_aug) also pays for its image transforms each step.
The first `--warmup` steps are excluded. Pause other CPU work while it runs.
`--device cuda` times the same steps on a GPU (bf16 autocast there is CUDA's; the CPU-only
variants, compile aside, mean nothing on it), synchronising before each clock read.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {
    "fp32": {},
    "fp32+channels_last": {"channels_last": True},
    "bf16": {"bf16": True},
    "bf16+channels_last": {"bf16": True, "channels_last": True},
    "bf16+compile": {"bf16": True, "compile": True},
    "bf16 1-thread": {"bf16": True, "threads": 1},
    "bf16 2-parts": {"bf16": True, "threads": 1, "parts": 2},
}


def child(preset_name: str, steps: int, warmup: int, opts: dict, device: str = "cpu",
          batch_size: int | None = None) -> dict:
    import torch

    sys.path.insert(0, str(ROOT))
    from lerobot.policies.factory import get_policy_class

    from so101_sim.train.augment import FrameAugmenter
    from so101_sim.train.presets import load_preset, make_config, policy_features
    from so101_sim.train.threads import BatchParts

    if opts.get("threads"):
        torch.set_num_threads(opts["threads"])
    torch.manual_seed(0)
    preset = load_preset(preset_name)
    cfg = make_config(preset, *policy_features(preset.image_size))
    cfg.device = device
    policy = get_policy_class(cfg.type)(cfg)  # DiffusionPolicy, or ACTPolicy for --preset act
    policy.to(device)
    policy.train()
    if opts.get("channels_last"):
        policy = policy.to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-4)
    b, h = batch_size or preset.train.batch_size, len(cfg.action_delta_indices)
    # the shapes the trainer's batches have: ACT's observations carry no time axis
    t = () if cfg.observation_delta_indices is None else (len(cfg.observation_delta_indices),)
    gen = torch.Generator().manual_seed(0)
    batch = {"observation.state": torch.rand(b, *t, 6, generator=gen) * 2 - 1,
             "action": torch.rand(b, h, 6, generator=gen) * 2 - 1,
             "action_is_pad": torch.zeros(b, h, dtype=torch.bool)}
    for cam in ("front", "side"):
        img = torch.rand(b, *t, 3, *preset.image_size, generator=gen)
        batch[f"observation.images.{cam}"] = img
    batch = {k: v.to(device) for k, v in batch.items()}

    forward = policy.forward
    if opts.get("compile"):
        forward = torch.compile(policy.forward)

    def batch_loss(part: dict) -> torch.Tensor:
        with torch.autocast(device, dtype=torch.bfloat16, enabled=bool(opts.get("bf16"))):
            return forward(part)[0]

    run_parts = BatchParts()
    # a preset with [augment] (cpu_aug) pays for its transforms every step, as in the trainer
    augment = FrameAugmenter(preset.augment) if preset.augment else dict

    def step() -> float:
        opt.zero_grad(set_to_none=True)
        loss = run_parts(batch_loss, augment(dict(batch)), opts.get("parts", 1))
        opt.step()
        return loss

    def sync() -> None:
        if device == "cuda":
            torch.cuda.synchronize()

    t0 = time.perf_counter()
    for _ in range(warmup):
        step()
    sync()
    warm_s = time.perf_counter() - t0
    neighbour = (subprocess.Popen([sys.executable, "-c", "while True: pass"])
                 if opts.get("busy") else None)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    sync()
    dt = (time.perf_counter() - t0) / steps
    if neighbour is not None:
        neighbour.kill()
    run_parts.close()
    return {"step_s": dt, "samples_per_s": b / dt, "warmup_s": warm_s,
            "threads": torch.get_num_threads()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="cpu",
                   help="preset, or a comma list timed one after the other (e.g. cpu,act)")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--busy", action="store_true",
                   help="also time each variant beside one spinning process")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                   help="where the steps run (cuda: the GPU; default cpu)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="samples per step (default: the preset's)")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        opts = {**VARIANTS[args.child], "busy": args.busy}
        print(json.dumps(child(args.preset, args.steps, args.warmup, opts, args.device,
                               args.batch_size)))
        return
    print(f"preset {args.preset} on {args.device}, batch {args.batch_size or 'preset'}, "
          f"{args.steps} timed steps after {args.warmup} warm-up, "
          f"load average {os.getloadavg()[0]:.2f} at start")
    rows = []
    presets = args.preset.split(",")
    for preset, name in ((pr, v) for pr in presets for v in args.variants.split(",")):
        for busy in (False, True) if args.busy else (False,):
            r = subprocess.run([sys.executable, __file__, "--preset", preset, "--steps",
                                str(args.steps), "--warmup", str(args.warmup), "--child", name,
                                "--device", args.device]
                               + (["--batch-size", str(args.batch_size)] if args.batch_size else [])
                               + (["--busy"] if busy else []), capture_output=True, text=True)
            label = (f"{preset} " if len(presets) > 1 else "") + name + (", busy" if busy else "")
            if r.returncode != 0:
                print(f"{label}: failed: {r.stderr.strip().splitlines()[-1]}")
                continue
            rows.append((label, json.loads(r.stdout.strip().splitlines()[-1])))
    base = rows[0][1]["step_s"] if rows else 1.0
    print(f"\n| variant | threads | s/step | samples/s | vs {rows[0][0]} | warm-up s |")
    print("|---|---|---|---|---|---|")
    for name, r in rows:
        print(f"| {name} | {r['threads']} | {r['step_s']:.3f} | {r['samples_per_s']:.1f} | "
              f"{base / r['step_s']:.2f}x | {r['warmup_s']:.1f} |")
    print(f"load average {os.getloadavg()[0]:.2f} at end")


if __name__ == "__main__":
    main()
