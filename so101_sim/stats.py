"""Success-rate statistics: Wilson intervals, exact binomial tails, episodes needed for a test.

Pure `math` (scipy is not a dependency), so reports and regression tests can use it without
numpy or torch. Rates are fractions in [0, 1] here; reports multiply by 100.
"""

from __future__ import annotations

import math

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


def _check_counts(successes: int, n: int) -> None:
    if n < 0 or not 0 <= successes <= n:
        raise ValueError(f"successes={successes}, n={n} are invalid; expected 0 <= successes <= n")
