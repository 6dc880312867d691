"""Success-rate statistics: Wilson intervals, exact binomial tails, episodes needed for a test,
and the paired (same-seed) forms: exact McNemar tests and Newcombe's paired interval.

Pure `math` (scipy is not a dependency), so reports and regression tests can use it without
numpy or torch. Rates are fractions in [0, 1] here; reports multiply by 100.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any, NamedTuple

Z95 = 1.959963984540054  # two-sided 95% normal quantile


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for `successes` out of `n` (95% by default).

    Unlike the normal approximation it stays inside [0, 1] and is honest at 0/n and n/n, which
    are the common cases for a good policy.
    """
    _check_counts(successes, n)
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # 0/n and n/n: the bound is exactly 0 (or 1); rounding must not push it past the rate
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return lo, hi


def binom_cdf(k: int, n: int, p: float) -> float:
    """P(X <= k) for X ~ Binomial(n, p), summed exactly in log space (no overflow for big n)."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"p={p} is invalid; expected a probability in [0, 1]")
    if k < 0:
        return 0.0
    if k >= n:
        return 1.0
    if p == 0.0:
        return 1.0
    if p == 1.0:
        return 0.0
    log_p, log_q = math.log(p), math.log1p(-p)
    lg_n = math.lgamma(n + 1)
    terms = [lg_n - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * log_p + (n - i) * log_q
             for i in range(k + 1)]
    top = max(terms)
    return min(1.0, math.exp(top) * math.fsum(math.exp(t - top) for t in terms))


def p_value_below(successes: int, n: int, baseline: float) -> float:
    """One-sided exact binomial p-value of H1 "the success rate is below `baseline`".

    The probability, if the true rate were `baseline`, of seeing `successes` or fewer.
    """
    _check_counts(successes, n)
    return binom_cdf(successes, n, baseline)


def critical_successes(n: int, baseline: float, alpha: float) -> int:
    """Largest success count that the one-sided test at level `alpha` rejects (-1 if none)."""
    if baseline >= 1.0:
        return n - 1  # at a baseline of 1, any failure is impossible under H0
    if baseline <= 0.0:
        return -1
    log_p, log_q, lg_n = math.log(baseline), math.log1p(-baseline), math.lgamma(n + 1)
    cdf = 0.0
    for k in range(n + 1):  # pmf terms summed upwards; tiny ones underflow to 0 harmlessly
        cdf += math.exp(lg_n - math.lgamma(k + 1) - math.lgamma(n - k + 1)
                        + k * log_p + (n - k) * log_q)
        if cdf > alpha:
            return k - 1
    return n


def power_below(n: int, baseline: float, true_rate: float, alpha: float) -> float:
    """Probability that `n` episodes at `true_rate` fail the test against `baseline`."""
    return binom_cdf(critical_successes(n, baseline, alpha), n, true_rate)


def episodes_needed(baseline: float, true_rate: float, alpha: float = 0.01,
                    power: float = 0.8, max_n: int = 5000) -> int:
    """Smallest N at which a drop from `baseline` to `true_rate` fails the test with `power`.

    Exact binomial power is a sawtooth in N (the critical count moves in integer steps), so a
    slightly larger N can have slightly less power; this returns the first N that reaches it.
    """
    if not 0.0 <= true_rate < baseline <= 1.0:
        raise ValueError(f"true_rate={true_rate}, baseline={baseline} are invalid; expected "
                         "0 <= true_rate < baseline <= 1 (a drop to detect)")
    for n in range(1, max_n + 1):
        if power_below(n, baseline, true_rate, alpha) >= power:
            return n
    raise ValueError(f"no N <= {max_n} detects {baseline} -> {true_rate} with power {power} at "
                     f"alpha={alpha}; test a larger drop or raise max_n")


def episodes_needed_measured(baseline: float, true_rate: float, alpha: float = 0.01,
                             power: float = 0.8, max_n: int = 5000) -> int:
    """Like ``episodes_needed``, but as the one-sample test is used in practice: its baseline
    is the lower Wilson bound of a baseline run on as many seeds (N) as the candidate gets, so
    the baseline's own noise costs power. The fair match for ``paired_episodes_needed``, which
    spends the same 2N episodes."""
    if not 0.0 <= true_rate < baseline <= 1.0:
        raise ValueError(f"true_rate={true_rate}, baseline={baseline} are invalid; expected "
                         "0 <= true_rate < baseline <= 1 (a drop to detect)")
    for n in range(1, max_n + 1):
        got = 0.0
        for k in range(n + 1):  # the baseline run's successes, Binomial(n, baseline)
            log_pk = (math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)
                      + (k * math.log(baseline) if k else 0.0)
                      + ((n - k) * math.log1p(-baseline) if n - k else 0.0))
            base = wilson_interval(k, n)[0]
            if log_pk > -40 and base > true_rate:
                got += math.exp(log_pk) * power_below(n, base, true_rate, alpha)
        if got >= power:
            return n
    raise ValueError(f"no N <= {max_n} detects {baseline} -> {true_rate} with power {power} at "
                     f"alpha={alpha}; test a larger drop or raise max_n")


# ----------------------------------------------------------------------- paired (same seeds)
class PairedSplit(NamedTuple):
    """The seeds two runs share, by outcome, each list in seed order."""

    both: list
    only_a: list
    only_b: list
    neither: list


def paired_split(a: Mapping[Any, bool], b: Mapping[Any, bool]) -> PairedSplit:
    """Split the seeds in both `a` and `b` (seed -> success) into the paired table's cells:
    the counts `mcnemar_p_value` and `paired_difference_interval` take."""
    split = PairedSplit([], [], [], [])
    for seed in sorted(a.keys() & b.keys()):
        cell = ((split.both if b[seed] else split.only_a) if a[seed] else
                (split.only_b if b[seed] else split.neither))
        cell.append(seed)
    return split


def mcnemar_p_value(only_a: int, only_b: int, alternative: str = "two-sided") -> float:
    """Exact McNemar p-value from the discordant seeds (A succeeded alone / B alone).

    Under H0 "same success rate" each discordant seed is a fair coin, so only_a ~
    Binomial(only_a + only_b, 1/2). ``alternative="less"``: H1 "A's rate is lower than B's"
    (one-sided, for regression tests); ``"two-sided"`` doubles the smaller tail (capped at 1).
    Concordant seeds carry no information about the difference and do not enter.
    """
    if only_a < 0 or only_b < 0:
        raise ValueError(f"only_a={only_a}, only_b={only_b} are invalid; expected counts >= 0")
    m = only_a + only_b
    if alternative == "less":
        return binom_cdf(only_a, m, 0.5)
    if alternative != "two-sided":
        raise ValueError(f"alternative={alternative!r} is invalid; expected 'two-sided' or "
                         "'less'")
    return 1.0 if m == 0 else min(1.0, 2.0 * binom_cdf(min(only_a, only_b), m, 0.5))


def paired_difference_interval(both: int, only_a: int, only_b: int, neither: int,
                               z: float = Z95) -> tuple[float, float]:
    """95% interval for rate(A) - rate(B) on the same seeds: Newcombe's hybrid score interval
    for paired proportions (Newcombe 1998, Stat Med 17:2635, method 10).

    It combines the two Wilson intervals with the phi correlation of the paired table, so it
    stays inside [-1, 1], is honest at 0/n and n/n, and is narrow when the runs agree on most
    seeds (which the unpaired interval cannot see).
    """
    for name, v in (("both", both), ("only_a", only_a), ("only_b", only_b), ("neither", neither)):
        if v < 0:
            raise ValueError(f"{name}={v} is invalid; expected a count >= 0")
    n = both + only_a + only_b + neither
    if n == 0:
        return -1.0, 1.0
    p1, p2 = (both + only_a) / n, (both + only_b) / n
    l1, u1 = wilson_interval(both + only_a, n, z)
    l2, u2 = wilson_interval(both + only_b, n, z)
    margins = (both + only_a) * (only_b + neither) * (both + only_b) * (only_a + neither)
    cross = both * neither - only_a * only_b
    # Newcombe's continuity correction of phi: positive association shrinks by n/2
    cross = max(cross - n / 2, 0.0) if cross > 0 else cross
    phi = cross / math.sqrt(margins) if margins else 0.0
    d = p1 - p2
    lo = d - math.sqrt(max(0.0, (p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2)
                           + (u2 - p2) ** 2))
    hi = d + math.sqrt(max(0.0, (p2 - l2) ** 2 - 2 * phi * (p2 - l2) * (u1 - p1)
                           + (u1 - p1) ** 2))
    return max(-1.0, lo), min(1.0, hi)


def paired_power(n: int, baseline: float, true_rate: float, discordant: float | None = None,
                 alpha: float = 0.01) -> float:
    """Probability that the one-sided exact McNemar test at `alpha` flags a drop from
    `baseline` to `true_rate` with `n` paired seeds.

    `discordant` is the fraction of seeds on which the two policies disagree (at least the
    drop). None assumes independent outcomes per seed, the worst realistic case; policies of
    one family trained alike disagree on far fewer seeds, which is where pairing pays.
    """
    only_base, only_cand = _discordant_split(baseline, true_rate, discordant)
    d = only_base + only_cand
    r = only_cand / d  # P(the candidate is the one that succeeded | discordant)
    log_d, log_nd = math.log(d), (math.log1p(-d) if d < 1 else -math.inf)
    lg_n = math.lgamma(n + 1)
    total = 0.0
    for m in range(n + 1):
        log_pm = lg_n - math.lgamma(m + 1) - math.lgamma(n - m + 1) + m * log_d
        if n - m:
            log_pm += (n - m) * log_nd
        if log_pm < -60:  # below 1e-26: no contribution
            continue
        total += math.exp(log_pm) * _conditional_power(m, r, alpha)
    return min(1.0, total)


def paired_episodes_needed(baseline: float, true_rate: float, discordant: float | None = None,
                           alpha: float = 0.01, power: float = 0.8, max_n: int = 5000) -> int:
    """Smallest number of paired seeds at which the one-sided McNemar test catches a drop from
    `baseline` to `true_rate` with `power` (see ``paired_power``; compare ``episodes_needed``
    for the one-sample test against a known baseline rate)."""
    _discordant_split(baseline, true_rate, discordant)  # validates before the search
    for n in range(1, max_n + 1):
        if paired_power(n, baseline, true_rate, discordant, alpha) >= power:
            return n
    raise ValueError(f"no N <= {max_n} detects {baseline} -> {true_rate} (discordant "
                     f"{discordant}) with power {power} at alpha={alpha}; raise max_n")


def _discordant_split(baseline: float, true_rate: float,
                      discordant: float | None) -> tuple[float, float]:
    """(P(only the baseline succeeds), P(only the candidate succeeds)) per seed."""
    if not 0.0 <= true_rate < baseline <= 1.0:
        raise ValueError(f"true_rate={true_rate}, baseline={baseline} are invalid; expected "
                         "0 <= true_rate < baseline <= 1 (a drop to detect)")
    drop = baseline - true_rate
    if discordant is None:
        return baseline * (1 - true_rate), true_rate * (1 - baseline)
    most = min(baseline + true_rate, 2 - baseline - true_rate)
    if not drop - 1e-12 <= discordant <= most + 1e-12:
        raise ValueError(f"discordant={discordant} is invalid for {baseline} -> {true_rate}; "
                         f"expected a fraction of seeds in [{drop:.4g}, {most:.4g}] (at least "
                         "the drop: the seeds the candidate lost)")
    return (discordant + drop) / 2, max(0.0, (discordant - drop) / 2)


@functools.lru_cache(maxsize=65536)
def _conditional_power(m: int, r: float, alpha: float) -> float:
    """P(reject | m discordant seeds), each won by the candidate with probability r."""
    k = critical_successes(m, 0.5, alpha)
    return binom_cdf(k, m, r) if k >= 0 else 0.0


def _check_counts(successes: int, n: int) -> None:
    if n < 0 or not 0 <= successes <= n:
        raise ValueError(f"successes={successes}, n={n} are invalid; expected 0 <= successes <= n")


__all__ = [
    "Z95",
    "PairedSplit",
    "binom_cdf",
    "critical_successes",
    "episodes_needed",
    "episodes_needed_measured",
    "mcnemar_p_value",
    "p_value_below",
    "paired_difference_interval",
    "paired_episodes_needed",
    "paired_power",
    "paired_split",
    "power_below",
    "wilson_interval",
]
