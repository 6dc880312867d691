"""What one policy forward costs per row at 8, 16, 32 rows, and whether the rows keep their bits.

    .venv/bin/python benchmarks/bench_forward_rows.py [CHECKPOINT] [--rows 8,16,32] [--repeats 10]
    .venv/bin/python benchmarks/bench_forward_rows.py --pooling-ab   # the pooling swap, A/B
    .venv/bin/python benchmarks/bench_forward_rows.py --trace-ab     # the traced U-Net, A/B

The harness pads every forward to the policy's ``batch_size`` rows (8 by default) because a
row's actions change bitwise with the batch size on CPU. This prints, per batch size, the
median time of a whole ``predict_chunks`` call (preprocessing, encoder, DDIM sampling,
postprocessing) on one torch thread, as each of the harness's forward threads runs it, over
rounds through the sizes in turn; the encoder's share; the cost per row; and whether the first
8 rows' actions equal those of an 8-row forward bit for bit. It answers how much a larger
default batch would save, and what it would cost: every earlier run's actions. Run it with
nothing else busy (pause training).

``--pooling-ab`` instead times an 8-row forward with the harness's channels-last max pooling
(``harness.policies.pooling``, what every loaded policy uses) against torch's default kernel,
in alternating rounds, and checks that the actions keep their bits. ``--trace-ab`` does the
same for the traced U-Net (``harness.policies.traced``) against the eager one.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from so101_sim.harness.policies.lerobot import LeRobotPolicy
from so101_sim.harness.policies.pooling import use_default_pooling
from so101_sim.harness.policies.protocol import ChunkRequest
from so101_sim.harness.policies.traced import use_eager_unet

ROOT = Path(__file__).resolve().parents[1]
BASE = 8  # the harness's default rows per forward


def requests(policy: LeRobotPolicy, n: int, seed: int = 0) -> list[ChunkRequest]:
    """`n` chunk requests with random frames and joint positions, as the workers send them."""
    rng = np.random.default_rng(seed)
    h, w = policy.info.image_size
    out = []
    for slot in range(n):
        history = [{"agent_pos": rng.uniform(-1, 1, 6).astype(np.float32),
                    "pixels": {c: rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
                               for c in policy.info.cameras}}
                   for _ in range(policy.info.n_obs_steps)]
        out.append(ChunkRequest(slot, 1000 + slot, history))
    return out


def chunks(policy: LeRobotPolicy, reqs: list[ChunkRequest]) -> np.ndarray:
    """One forward with every slot's noise drawn afresh from its episode seed."""
    for r in reqs:
        policy.start_episode(r.slot, r.seed)
    return policy.predict_chunks(reqs)


def seconds(fn) -> float:
    """Wall time of one call of `fn`."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


#: --ab: what each A/B undoes in the "plain" policy, and the two rows' labels.
AB = {
    "pooling": (use_default_pooling, "max pooling", "torch's default kernel",
                "channels-last (harness)"),
    "trace": (use_eager_unet, "U-Net", "eager modules", "traced graph (harness)"),
}


def speedup_ab(checkpoint: str, repeats: int, kind: str) -> None:
    """8-row forwards as the harness runs them against one speed-up undone, alternating."""
    undo, what, plain_label, fast_label = AB[kind]
    quiet = lambda _: None  # noqa: E731
    fast = LeRobotPolicy(checkpoint, batch_size=BASE, log=quiet)
    plain = LeRobotPolicy(checkpoint, batch_size=BASE, log=quiet)
    undone = undo(plain.policy)
    print(f"{checkpoint}: {undone} {what} module(s) undone; one torch thread, "
          f"median of {repeats} alternating rounds\n")
    reqs = requests(fast, BASE)
    same = bool(np.array_equal(chunks(fast, reqs), chunks(plain, reqs)))
    times: dict[str, list[float]] = {plain_label: [], fast_label: []}
    for _ in range(repeats):
        times[plain_label].append(seconds(lambda: chunks(plain, reqs)))
        times[fast_label].append(seconds(lambda: chunks(fast, reqs)))
    print(f"| {what} | 8-row forward ms | vs {plain_label} |\n|---|---|---|")
    base = statistics.median(times[plain_label])
    for label, ts in times.items():
        f = statistics.median(ts)
        print(f"| {label} | {f * 1e3:.1f} | {f / base:.3f}x |")
    print(f"\nactions bit for bit the same: {'yes' if same else 'NO'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", nargs="?", default=str(ROOT / "policy/pick_place_diffusion"))
    parser.add_argument("--rows", default="8,16,32", help="batch sizes, comma-separated")
    parser.add_argument("--repeats", type=int, default=10, help="rounds of one forward per size")
    parser.add_argument("--pooling-ab", action="store_true",
                        help="time the channels-last max pooling against torch's default")
    parser.add_argument("--trace-ab", action="store_true",
                        help="time the traced U-Net against the eager one")
    args = parser.parse_args()
    torch.set_num_threads(1)  # as each of the harness's two forward threads runs
    for kind, asked in (("pooling", args.pooling_ab), ("trace", args.trace_ab)):
        if asked:
            speedup_ab(args.checkpoint, args.repeats, kind)
            return
    sizes = [int(x) for x in args.rows.split(",")]
    if any(n < BASE for n in sizes):
        parser.error(f"--rows {args.rows}: every size must be >= {BASE} (the bit check compares "
                     f"the first {BASE} rows with an {BASE}-row forward)")
    quiet = lambda _: None  # noqa: E731
    base = LeRobotPolicy(args.checkpoint, batch_size=BASE, log=quiet)
    ref = chunks(base, requests(base, BASE))
    policies = {n: base if n == BASE else LeRobotPolicy(args.checkpoint, batch_size=n, log=quiet)
                for n in sizes}
    reqs = {n: requests(policies[n], n) for n in sizes}
    imgs = {}
    for n, policy in policies.items():
        chunks(policy, reqs[n])  # warm-up
        h, w = getattr(policy.cfg, "crop_shape", None) or policy.info.image_size
        n_img = n * policy.info.n_obs_steps * len(policy.info.cameras)
        imgs[n] = torch.rand((n_img, 3, h, w), generator=torch.Generator().manual_seed(0))
    # Rounds over the sizes in turn, so drift in this machine's speed hits every size alike.
    fwd: dict[int, list[float]] = {n: [] for n in sizes}
    enc: dict[int, list[float]] = {n: [] for n in sizes}
    for _ in range(args.repeats):
        for n, policy in policies.items():
            fwd[n].append(seconds(lambda p=policy, r=reqs[n]: chunks(p, r)))
            inner = getattr(policy.policy, "diffusion", None)  # diffusion: the image encoder
            if inner is not None:
                with torch.no_grad():
                    enc[n].append(seconds(lambda i=imgs[n], m=inner: m.rgb_encoder(i)))
    print(f"{args.checkpoint}: one torch thread, median of {args.repeats} rounds over the "
          "sizes in turn\n")
    print("| rows | forward ms | encoder ms | rest ms | ms per row | per row vs first | "
          "first 8 rows same bits as an 8-row forward |")
    print("|---|---|---|---|---|---|---|")
    first = None
    for n, policy in policies.items():
        f = statistics.median(fwd[n])
        e = statistics.median(enc[n]) if enc[n] else float("nan")
        same = bool(np.array_equal(chunks(policy, reqs[n])[:BASE], ref))
        per_row = f / n
        first = first or per_row
        print(f"| {n} | {f * 1e3:.1f} | {e * 1e3:.1f} | {(f - e) * 1e3:.1f} | "
              f"{per_row * 1e3:.2f} | {per_row / first:.2f}x | {'yes' if same else 'no'} |")


if __name__ == "__main__":
    main()
