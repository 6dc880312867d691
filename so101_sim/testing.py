"""Success-rate regression tests that fail on real drops, not on noise.

``assert_success_rate(policy, baseline=..., episodes=N)`` runs N evaluation episodes and fails
only when the success rate is significantly below ``baseline``: a one-sided exact binomial
test, H0 "the rate is `baseline`" against H1 "it is lower", at level ``alpha`` (default 0.01,
so a policy as good as its baseline fails CI in at most 1% of runs). It prints the rate, its
95% Wilson interval, the baseline and the p-value either way.

Choosing the baseline: a rate measured as k/n is itself uncertain; pass the lower end of its
Wilson interval (``so101_sim.harness.stats.wilson_interval(k, n)[0]``), e.g. 500/500 ->
0.992, so the baseline's own noise cannot fail the test. A baseline of exactly 1.0 fails on
any failure.

Choosing N: the test detects a drop only with some probability (power). The smallest N that
catches a drop from ``baseline`` to ``true_rate`` with 80% power at alpha = 0.01
(``so101_sim.harness.stats.episodes_needed``):

    baseline -> true rate    N      |  baseline -> true rate    N
    0.99 -> 0.90            42      |  0.90 -> 0.80           122
    0.95 -> 0.85            82      |  0.80 -> 0.60            52
    0.95 -> 0.90           267      |  0.50 -> 0.30            64

Halving the drop roughly quadruples N. With fewer episodes the test still never fails a
policy at its baseline more often than alpha; it just misses smaller drops.

The N episodes stop early once the ones still to run can no longer change the verdict
(curtailed sampling): after enough successes the test passes whatever the rest do, after
enough failures it fails. The verdict is exactly the fixed-N test's, so its error rates are
too; only the time shrinks (the reported p-value is then the bound that decided it).

The paired form, ``assert_not_worse(candidate, baseline_run)``, reruns the seeds of a recorded
``so101-sim eval`` folder in order and fails only on a significant drop seed by seed: an
anytime-valid sequential test stops it as soon as the answer is known, and the one-sided exact
McNemar test decides if every seed ran undecided. It needs no well-measured baseline rate,
and it needs fewer episodes than the one-sample test whenever that test's baseline is itself
measured on N seeds; against a baseline known exactly it wins only when the policies disagree
on few seeds beyond the lost ones (README, "Comparing two policies";
``so101_sim.harness.stats.paired_episodes_needed``).
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from so101_sim.dataset import EVAL_SEED_START
from so101_sim.harness.stats import p_value_below, wilson_interval
from so101_sim.tasks import DEFAULT_TASK


@dataclass(frozen=True)
class RateCheck:
    """The outcome of one success-rate test."""

    successes: int
    n: int
    baseline: float
    alpha: float
    p_value: float  # over all n; if ran < n, the bound that decided (see line())
    ci95: tuple[float, float]
    ran: int | None = None  # episodes run before the verdict was certain (None: all n)

    @property
    def episodes_run(self) -> int:
        return self.n if self.ran is None else self.ran

    @property
    def rate(self) -> float:
        return self.successes / self.episodes_run

    @property
    def passed(self) -> bool:
        return self.p_value >= self.alpha

    def line(self) -> str:
        lo, hi = self.ci95
        verdict = "OK" if self.passed else "SIGNIFICANTLY BELOW BASELINE"
        p, early = f"p = {self.p_value:.4g}", ""
        if self.episodes_run < self.n:
            p = f"p {'>=' if self.passed else '<='} {self.p_value:.4g} over all {self.n}"
            early = (f", decided after {self.episodes_run} of {self.n} episodes (the other "
                     f"{self.n - self.episodes_run} could not change the verdict)")
        return (f"success {self.successes}/{self.episodes_run} = {100 * self.rate:.1f}% (95% "
                f"Wilson {100 * lo:.1f}-{100 * hi:.1f}%){early}, baseline "
                f"{100 * self.baseline:.1f}%, one-sided binomial {p} (alpha {self.alpha}): "
                f"{verdict}")


def check_success_rate(successes: int, n: int, baseline: float,
                       alpha: float = 0.01, ran: int | None = None) -> RateCheck:
    """Test `successes`/`n` against `baseline` (fractions); see the module docstring.

    `ran` < `n`: only `ran` of the test's `n` episodes ran, and `successes` already decide
    the test whatever the other n - ran give; raises ValueError if they do not."""
    _check_level(alpha, baseline)
    runs = n if ran is None else ran
    if not 0 < runs <= n:
        raise ValueError(f"ran={ran} is invalid; expected 1 to n={n} episodes")
    verdict = curtailed_verdict(successes, runs, n, baseline, alpha)
    if verdict is None:
        raise ValueError(f"{successes}/{runs} of {n} episodes do not decide the test yet; "
                         "run all of them")
    # the p-value over all n that the unseen episodes could least move towards the other side
    p = p_value_below(successes + (n - runs) * (verdict == "fail"), n, baseline)
    return RateCheck(successes, n, baseline, alpha, p, wilson_interval(successes, runs),
                     None if runs == n else runs)


def curtailed_verdict(successes: int, ran: int, n: int, baseline: float,
                      alpha: float) -> str | None:
    """"pass" or "fail" if the one-sided test on `n` episodes is decided by `successes` in the
    first `ran` of them, whatever the other n - ran give; None while it is not."""
    if p_value_below(successes, n, baseline) >= alpha:  # even if every other one fails
        return "pass"
    if p_value_below(successes + n - ran, n, baseline) < alpha:  # even if every other succeeds
        return "fail"
    return None


class CurtailedTest:
    """``evaluate``'s stop hook for `assert_success_rate`: stops the run as soon as the
    episodes still to run cannot change the fixed-size test's verdict."""

    def __init__(self, n: int, baseline: float, alpha: float) -> None:
        self.n, self.baseline, self.alpha = n, baseline, alpha
        self.successes = self.ran = 0
        self.verdict: str | None = None

    def update(self, done: dict[int, Any]) -> bool:
        self.ran, self.successes = len(done), sum(bool(r.success) for r in done.values())
        self.verdict = curtailed_verdict(self.successes, self.ran, self.n, self.baseline,
                                         self.alpha)
        return self.verdict is not None

    def to_info(self) -> dict[str, Any]:
        return {"verdict": self.verdict or "undecided", "episodes": self.ran, "of": self.n,
                "successes": self.successes,
                "test": "curtailed one-sided exact binomial (the fixed-size test's verdict, "
                        "known before every episode ran)"}


def assert_success_rate(policy: Any, *, baseline: float, episodes: int,
                        alpha: float = 0.01, task: str = DEFAULT_TASK,
                        seed_start: int = EVAL_SEED_START, n_envs: int = 2,
                        out_dir: str | Path | None = None, **evaluate_kwargs: Any) -> RateCheck:
    """Evaluate `policy` ("expert", a checkpoint directory or an ``EvalPolicy``) on
    `episodes` seeds and fail the calling test if its success rate is significantly below
    `baseline`; the run stops as soon as the seeds left cannot change that verdict.
    Returns the ``RateCheck`` when it passes."""
    from so101_sim.harness import evaluate

    _check_level(alpha, baseline)  # before any episode runs
    evaluate_kwargs = {"videos": 0, "progress": False, "report": False, **evaluate_kwargs}
    stop = CurtailedTest(episodes, baseline, alpha)
    with tempfile.TemporaryDirectory(prefix="so101_rate_") as tmp:
        result = evaluate(policy, task=task, episodes=episodes, n_envs=n_envs,
                          seed_start=seed_start, out_dir=out_dir or Path(tmp) / "eval",
                          stop=stop, log=lambda _: None, **evaluate_kwargs)
    agg = result["aggregated"]
    check = check_success_rate(agg["n_success"], episodes, baseline, alpha,
                               ran=agg["n_episodes"])
    print(f"{result['config']['policy']} on {result['config']['task']}: {check.line()}; "
          f"failures {agg['failure_modes'] or 'none'}")
    if not check.passed:
        _fail(f"success rate regression: {check.line()}; failure modes {agg['failure_modes']}")
    return check


@dataclass(frozen=True)
class PairedCheck:
    """The outcome of one paired (same-seed) test of a candidate against a baseline run."""

    comparison: dict[str, Any]  # so101_sim.harness.compare's result, A = candidate
    alpha: float
    p_value: float  # one-sided exact McNemar on the seeds run, H1 "the candidate is worse"
    sequential: dict[str, Any] | None = None  # the sequential verdict (harness.sequential)

    @property
    def passed(self) -> bool:
        verdict = (self.sequential or {}).get("verdict", "undecided")
        if verdict != "undecided":
            return verdict == "not worse"
        return self.p_value >= self.alpha / 2  # every seed ran: the fixed test's half of alpha

    def line(self) -> str:
        r, p = self.comparison, self.comparison["paired"]
        lo, hi = r["difference_ci95_pp"]
        verdict = "OK" if self.passed else "SIGNIFICANTLY WORSE THAN BASELINE"
        seq = ""
        if self.sequential is not None:
            seq = (f"sequential test: {self.sequential['verdict']} after "
                   f"{self.sequential['episodes']} episodes; ")
        return (f"candidate {r['a']['n_success']}/{r['n_seeds']} vs baseline "
                f"{r['b']['n_success']}/{r['n_seeds']} on the same seeds (only candidate "
                f"{p['only_a']}, only baseline {p['only_b']}); difference "
                f"{r['difference_pp']:+.1f} points (95% CI {lo:+.1f} to {hi:+.1f}); {seq}"
                f"one-sided exact McNemar p = {self.p_value:.4g} (alpha {self.alpha}): "
                f"{verdict}")


def assert_not_worse(candidate: Any, baseline_run: str | Path, *, alpha: float = 0.01,
                     task: str | Path | None = None, n_envs: int = 2,
                     out_dir: str | Path | None = None, **evaluate_kwargs: Any) -> PairedCheck:
    """Evaluate `candidate` on the seeds and task of `baseline_run` (an ``so101-sim eval``
    folder), in order, and fail the calling test only if it is worse seed by seed.

    The seeds run under the anytime-valid sequential paired test of ``harness.sequential`` at
    alpha / 2, which stops as soon as it can say "worse" (fail) or "not worse" (pass); if it
    is still undecided after every seed, the one-sided exact McNemar test on all of them
    decides at the other alpha / 2. A candidate as good as the baseline fails with
    probability at most `alpha` in all. `task` defaults to the baseline's task name (pass the
    .toml path if the baseline ran a task file outside envs/).
    """
    import dataclasses

    from so101_sim.harness.against import evaluate_against
    from so101_sim.harness.compare import check_comparable, load_run, paired_result
    from so101_sim.harness.stats import mcnemar_p_value

    _check_level(alpha)
    base = load_run(baseline_run)
    evaluate_kwargs = {"videos": 0, "progress": False, "report": False, **evaluate_kwargs}
    with tempfile.TemporaryDirectory(prefix="so101_paired_") as tmp:
        out = Path(out_dir) if out_dir else Path(tmp) / "eval"
        result = evaluate_against(candidate, baseline_run, alpha=alpha / 2, task=task,
                                  n_envs=n_envs, out_dir=out, log=lambda _: None,
                                  **evaluate_kwargs)
        cand = load_run(out)
    ran = sorted(cand.success)
    base = dataclasses.replace(base, success={s: base.success[s] for s in ran},
                               actions_sha={s: base.actions_sha.get(s) for s in ran})
    check_comparable(cand, base)
    r = paired_result(cand, base)
    check = PairedCheck(r, alpha, mcnemar_p_value(r["paired"]["only_a"], r["paired"]["only_b"],
                                                  alternative="less"),
                        result["sequential_verdict"])
    print(f"{cand.policy} vs baseline {base.policy} ({baseline_run}) on {base.task}: "
          f"{check.line()}")
    if not check.passed:
        _fail(f"paired regression: {check.line()}; seeds only the baseline solved: "
              f"{r['seeds_only_b'][:20]}")
    return check


def _check_level(alpha: float, baseline: float | None = None) -> None:
    if baseline is not None and not 0.0 < baseline <= 1.0:
        raise ValueError(f"baseline={baseline} is invalid; expected a success rate in (0, 1] "
                         "as a fraction (0.95, not 95)")
    if not 0.0 < alpha < 0.5:
        raise ValueError(f"alpha={alpha} is invalid; expected a small level such as 0.01")


def _fail(message: str) -> None:
    try:
        import pytest
    except ImportError:  # used outside pytest
        raise AssertionError(message) from None
    pytest.fail(message, pytrace=False)
