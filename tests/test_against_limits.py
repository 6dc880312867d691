"""benchmarks/against_limits.py's curtailment: a verdict is called early exactly when every
outcome of the unfinished seeds gives it, so curtailing could never change a verdict."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
from script_loader import load_script

from so101_sim.harness.sequential import UNDECIDED, batch_verdicts

LIMITS = load_script(Path(__file__).resolve().parents[1] / "benchmarks" / "against_limits.py")


def _every_completion(a: np.ndarray, b: np.ndarray, done: np.ndarray) -> set[str]:
    """The prefix test's verdict on the full sequence, for every outcome of the unfinished seeds."""
    pending = np.flatnonzero(~done)
    rows = []
    for outcome in itertools.product((0, 1), repeat=len(pending)):
        row = b.copy()
        row[pending] = outcome
        rows.append(row)
    verdicts, _ = batch_verdicts(np.tile(a, (len(rows), 1)), np.stack(rows))
    return set(verdicts.tolist())


def test_curtailed_verdicts_are_those_every_completion_gives() -> None:
    rng = np.random.default_rng(5)
    called = {"worse": 0, "not worse": 0, None: 0}
    for case in range(240):
        n = int(rng.integers(30, 120))
        a = (rng.random(n) < 0.9).astype(np.int64)
        # a clear regression, the same outcomes, or in between: every verdict gets exercised
        keep = (0.45, 1.0, 0.75)[case % 3]  # P(new succeeds | reference succeeded)
        b = np.where(a == 1, rng.random(n) < keep, rng.random(n) < 0.1).astype(np.int64)
        done = np.ones(n, dtype=bool)
        done[rng.choice(n, int(rng.integers(0, 9)), replace=False)] = False
        got = LIMITS.decide(a, b, done, curtail=True)
        verdicts = _every_completion(a, b, done)
        expected = next(iter(verdicts)) if len(verdicts) == 1 else None
        assert got == (None if expected == UNDECIDED else expected), (case, verdicts, got)
        called[got] += 1
    assert min(called.values()) >= 10, called  # each branch was reached, not just one


def test_without_curtailment_only_the_finished_prefix_counts() -> None:
    a = np.ones(40, dtype=np.int64)
    b = np.zeros(40, dtype=np.int64)  # every seed a loss: "worse" within a few
    done = np.ones(40, dtype=bool)
    done[0] = False  # the first seed still running holds the prefix test back
    assert LIMITS.decide(a, b, done, curtail=False) is None
    assert LIMITS.decide(a, b, done, curtail=True) == "worse"
    done[0] = True
    assert LIMITS.decide(a, b, done, curtail=False) == "worse"
