"""What, besides the per-episode cost, could shorten `eval --against`: offline, on measured runs.

    .venv/bin/python benchmarks/against_limits.py OUT [--reference RUN] [--draws 4000]

OUT is a `bench_against.py --out` folder after a run with windows: its weak_full* and
reference_* runs (RUN is the first window's reference when OUT has none of its own). Nothing
is simulated by MuJoCo here; the measured outcomes and episode lengths are replayed:

1. the test's stakes: the mixture's largest stake (`truncation`, shipped 0.75) against
   others, and the stake that is best in hindsight (a Kelly bet on the pooled pairs, which no
   test can know in advance), on random 200-seed draws from the pooled pairs;
2. dispatch: seeds go to C env slots in seed order and the test reads only the finished
   prefix, so at a verdict the other slots hold later seeds. The time the prefix test decides,
   over the time its n seeds would take packed perfectly, for C = 8, 12, 16 (at equal
   throughput, which on 2 cores it is not: fewer envs mean fewer rows per forward);
3. curtailment: deciding as soon as no outcome of the unfinished seeds can change the verdict.
   Payoffs are monotone in the new policy's success, so the verdict is certain exactly when the
   completion least favourable to it (every unfinished seed succeeds, for "worse"; fails, for
   "not worse") still gives it. The wall that would save, weakened and itself.
"""

from __future__ import annotations

import argparse
import heapq
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_against import paired

from so101_sim.harness.sequential import TRUNCATION, WORSE, batch_verdicts

SLOTS = (8, 12, 16)


def episodes(run_dir: Path) -> dict[int, tuple[bool, int]]:
    """seed -> (success, steps) from an eval folder's eval_info.json (data, read as JSON)."""
    info = json.loads((run_dir / "eval_info.json").read_text(encoding="utf-8"))
    return {int(e["seed"]): (bool(e["success"]), int(e["steps"])) for e in info["per_episode"]}


def windows(out: Path, reference: Path | None) -> list[tuple[dict, dict]]:
    """(reference, weakened) episodes per window, the first window first."""
    first = reference if reference is not None else out / "reference"
    pairs = [(episodes(first), episodes(out / "weak_full"))]
    for ref in sorted(out.glob("reference_*")):
        start = ref.name.split("_", 1)[1]
        pairs.append((episodes(ref), episodes(out / f"weak_full_{start}")))
    return pairs


def hindsight_episodes(a: np.ndarray, b: np.ndarray, lam: float,
                       alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Per row: whether one fixed stake lam on the discordant pairs reaches 1/alpha, and the
    episodes it takes (all of them if never)."""
    d = b.astype(np.int64) - a.astype(np.int64)
    log_k = np.cumsum(np.where(d == -1, np.log1p(lam), np.where(d == 1, np.log1p(-lam), 0.0)),
                      axis=1)
    hit = log_k >= np.log(1.0 / alpha)
    reached = hit.any(axis=1)
    return reached, np.where(reached, hit.argmax(axis=1) + 1, a.shape[1])


def stakes(ref: dict[int, bool], new: dict[int, bool], n: int, draws: int) -> None:
    a, b = paired(ref, new)
    rng = np.random.default_rng(0)
    picks = np.stack([rng.choice(len(a), n, replace=False) for _ in range(draws)])
    losses, wins = int((a & ~b.astype(bool)).sum()), int((~a.astype(bool) & b).sum())
    print(f"1. the test's stakes, on {draws} random {n}-seed draws from {len(a)} pooled pairs "
          f"({losses} losses, {wins} wins):")
    print("| stakes | 'worse' in | median episodes (all draws) | itself: median to 'not worse' |")
    print("|---|---|---|---|")
    for t in (0.5, TRUNCATION, 0.9):
        v, used = batch_verdicts(a[picks], b[picks], truncation=t)
        _, itself = batch_verdicts(a[picks], a[picks], truncation=t)
        shipped = " (shipped)" if t == TRUNCATION else ""
        print(f"| mixture up to {t:g} of the safe stake{shipped} | {(v == WORSE).mean():.1%} | "
              f"{np.median(used):.0f} | {np.median(itself):.0f} |")
    lam = (losses - wins) / (losses + wins)
    reached, used = hindsight_episodes(a[picks], b[picks], lam, 0.05)
    print(f"| one stake {lam:.2f}, best in hindsight (not a valid design) | "
          f"{reached.mean():.1%} | {np.median(used):.0f} | - |")


def decide(a: np.ndarray, b: np.ndarray, done: np.ndarray, curtail: bool) -> str | None:
    """The verdict the finished seeds settle, or None. Without curtailment only the finished
    prefix counts; with it, also seeds after an unfinished one, when no outcome of theirs
    could change the verdict."""
    if not curtail:
        n = int(done.argmin()) if not done.all() else len(done)
        v, _ = batch_verdicts(a[None, :n], b[None, :n]) if n else (np.array(["undecided"]), 0)
        return None if v[0] == "undecided" else str(v[0])
    for label, fill in ((WORSE, 1), ("not worse", 0)):
        least = np.where(done, b, fill)  # the completion least favourable to `label`
        v, _ = batch_verdicts(a[None, :], least[None, :])
        if v[0] == label:
            return label
    return None


def replay_dispatch(a: np.ndarray, b: np.ndarray, steps: np.ndarray, slots: int,
                    curtail: bool = False) -> tuple[str | None, float, int]:
    """Seeds to `slots` env slots in seed order, each slot a step per time unit: the verdict, the
    time it comes and the seeds dispatched by then."""
    heap = [(float(steps[i]), i) for i in range(min(slots, len(a)))]
    heapq.heapify(heap)
    done, sent = np.zeros(len(a), dtype=bool), len(heap)
    while heap:
        t, i = heapq.heappop(heap)
        done[i] = True
        if sent < len(a):
            heapq.heappush(heap, (t + steps[sent], sent))
            sent += 1
        v = decide(a[:sent], b[:sent], done[:sent], curtail)
        if v is not None:
            return v, t, sent
    return None, t, sent


def dispatch(runs: list[tuple[dict, dict]]) -> None:
    print("\n2. dispatch in seed order: the prefix test's verdict time over its seeds' packed "
          "time (mean of the windows; weakened against its window's reference)")
    print("| env slots | verdict time / packed time |")
    print("|---|---|")
    for slots in SLOTS:
        ratios = []
        for ref, weak in runs:
            seeds = sorted(set(ref) & set(weak))
            a = np.array([ref[s][0] for s in seeds], dtype=np.int64)
            b = np.array([weak[s][0] for s in seeds], dtype=np.int64)
            steps = np.array([weak[s][1] for s in seeds], dtype=np.float64)
            v, t, _ = replay_dispatch(a, b, steps, slots)
            if v is None:
                continue
            _, used = batch_verdicts(a[None, :], b[None, :])
            ratios.append(t / (steps[:used[0]].sum() / slots))
        print(f"| {slots} | {np.mean(ratios):.3f} |")


def curtailment(runs: list[tuple[dict, dict]], slots: int = 16) -> None:
    print(f"\n3. curtailment, {slots} env slots: when the prefix test and the curtailed one "
          "decide (time in steps of one slot)")
    print("| window | policy | prefix: verdict, time | curtailed: verdict, time | saved |")
    print("|---|---|---|---|---|")
    for k, (ref, weak) in enumerate(runs):
        seeds = sorted(set(ref) & set(weak))
        a = np.array([ref[s][0] for s in seeds], dtype=np.int64)
        for name, new in (("weakened", weak), ("itself", ref)):
            b = np.array([new[s][0] for s in seeds], dtype=np.int64)
            steps = np.array([new[s][1] for s in seeds], dtype=np.float64)
            pv, pt, _ = replay_dispatch(a, b, steps, slots)
            cv, ct, _ = replay_dispatch(a, b, steps, slots, curtail=True)
            print(f"| {k} | {name} | {pv}, {pt:.0f} | {cv}, {ct:.0f} | {1 - ct / pt:.1%} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="a bench_against.py --out folder with windows")
    parser.add_argument("--reference", type=Path, default=None,
                        help="the first window's reference run (default: OUT/reference)")
    parser.add_argument("--draws", type=int, default=4000)
    args = parser.parse_args()
    runs = windows(args.out, args.reference)
    ref_all = {s: ok for ref, _ in runs for s, (ok, _) in ref.items()}
    weak_all = {s: ok for _, weak in runs for s, (ok, _) in weak.items()}
    stakes(ref_all, weak_all, len(runs[0][0]), args.draws)
    dispatch(runs)
    curtailment(runs)


if __name__ == "__main__":
    main()
