"""Anytime-valid sequential paired test: stop ``eval --against RUN`` once the answer is known.

Each seed gives a pair (a, b): a = the reference run's success, b = the new policy's success on
the same seed. With d = b - a in {-1, 0, 1}, delta = E[d] = P(b) - P(a). Two one-sided tests run
side by side, each a betting capital on d (Waudby-Smith & Ramdas, "Estimating means of bounded
random variables by betting", JRSS-B 2023), for margin M and indifference width D:

* "worse" rejects H: delta >= -M with K_t = mean_j prod_i (1 + lam_j * (-M - d_i));
* "not worse" rejects H': delta <= -(M + D) with K'_t = mean_j prod_i (1 + lam_j * (d_i + M + D)).

Each lam_j is a fixed stake from a grid of 20 midpoints spread uniformly over (0, 3/4 of the
largest stake that keeps every factor positive), so for every distribution inside H each
factor has mean <= 1 and each product, hence their average, is a non-negative supermartingale
starting at 1 (a test supermartingale). Ville's inequality gives P(sup_t K_t >= 1/alpha) <=
alpha, so the error bound holds however the run stops, including after peeking at every
episode, with no normal approximation and no minimum sample size. The grid only affects power.

Why a fixed-stake mixture: a fixed stake's capital depends only on the counts of losses, ties
and wins, so nothing has to be learnt and nothing is random. Plug-in (aGRAPA) stakes were
tried first: simulating a 0.9 -> 0.8 regression (half the seeds equally hard for both), they
reached 78% power within 200 episodes against 85% for this mixture, because discordant pairs
are rare and the plug-in spends its first ones estimating what to bet.

At M = 0 the "worse" capital is exactly a mixture SPRT on the discordant pairs (L losses, W
wins): (1 + lam)^L (1 - lam)^W = q^L (1 - q)^W / (1/2)^(L+W) with q = (1 + lam) / 2. A tie
multiplies it by 1, as in McNemar's test, because concordant seeds say nothing about which
policy is better. Betting on d rather than on the discordant pairs alone keeps that and extends
it to M > 0, where the hypothesis is in absolute points and so depends on how often pairs
disagree, a nuisance the betting capital needs no conditioning for: ties then count, against
"worse" (a run of ties caps how fast the new policy can be losing) and for "not worse" (many
ties rule out a loss of M + D points).

``fixed_n_for_power`` is the fixed-size (normal-approximation McNemar) baseline used to show
what the sequential test saves. ``batch_verdicts`` runs the same arithmetic on many sequences
at once, for simulations.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

import numpy as np

from so101_sim.utils.text import counted

__all__ = ["NOT_WORSE", "UNDECIDED", "WORSE", "SequentialPairedTest", "Verdict",
           "batch_verdicts", "fixed_n_for_power", "sequential_verdict"]

WORSE, NOT_WORSE, UNDECIDED = "worse", "not worse", "undecided"
TRUNCATION = 0.75  # stakes reach 3/4 of the largest safe bet: one bad pair costs <= 75%
GRID = 20  # stakes in the mixture: more changes nothing measurable, fewer loses a little power


def _real(value: Any, name: str, expected: str, example: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be {expected}, got {value!r}; e.g. {example}")
    return float(value)


@dataclass(frozen=True)
class _Design:
    """The two nulls' boundaries, the stake caps and the rejection level, validated once."""

    margin: float
    indifference: float
    alpha: float
    max_episodes: int | None
    worse_table: np.ndarray  # (GRID, 3): log(1 + lam_j * y) for a loss, a tie, a win
    not_worse_table: np.ndarray
    log_threshold: float

    @classmethod
    def make(cls, margin: Any, indifference: Any, alpha: Any,
             max_episodes: Any, truncation: Any = TRUNCATION) -> _Design:
        m = _real(margin, "margin", "a fraction in [0, 1) (5 points = 0.05)",
                  "margin=0.05 (eval --margin 0.05)")
        if not 0 <= m < 1:
            raise ValueError(f"margin must be a fraction in [0, 1) (5 points = 0.05), got "
                             f"{margin!r}; e.g. margin=0.05 (eval --margin 0.05)")
        d = _real(indifference, "indifference", "a fraction > 0 (10 points = 0.10)",
                  "indifference=0.10 (eval --indifference 0.10)")
        if not d > 0:
            raise ValueError(f"indifference must be a fraction > 0 (10 points = 0.10), got "
                             f"{indifference!r}; e.g. indifference=0.10 (eval --indifference "
                             "0.10)")
        if not m + d < 2:
            raise ValueError(f"margin + indifference must be < 2 (delta lies in [-1, 1]), got "
                             f"margin={margin!r} + indifference={indifference!r} = {m + d!r}; "
                             "e.g. margin=0.05, indifference=0.10 (eval --margin 0.05 "
                             "--indifference 0.10)")
        a = _real(alpha, "alpha", "an error rate in (0, 0.5)", "alpha=0.05 (eval --alpha 0.05)")
        if not 0 < a < 0.5:
            raise ValueError(f"alpha must be an error rate in (0, 0.5), got {alpha!r}; "
                             "e.g. alpha=0.05 (eval --alpha 0.05)")
        if max_episodes is not None and (
                isinstance(max_episodes, bool) or not isinstance(max_episodes, numbers.Integral)
                or max_episodes < 1):
            raise ValueError(f"max_episodes must be None or an integer >= 1, got "
                             f"{max_episodes!r}; e.g. max_episodes=400 (eval --max-episodes 400)")
        t = _real(truncation, "truncation", "a fraction in (0, 1)", "truncation=0.75")
        if not 0 < t < 1:
            raise ValueError(f"truncation must be a fraction in (0, 1) of the largest safe "
                             f"stake, got {truncation!r}; e.g. truncation=0.75 (the default)")
        # Payoff per unit stake for (a loss, a tie, a win). "worse" bets the pair difference
        # falls below -margin: worst case -(1 + m) on a win. "not worse" bets it rises above
        # -(margin + indifference): worst case -(1 - m - d) on a loss; none when m + d >= 1,
        # where H' is at most the point delta = -1, any stake is safe and the tie payoff sets
        # the scale.
        y_worse = np.array([1.0 - m, -m, -1.0 - m])
        y_not_worse = np.array([m + d - 1.0, m + d, 1.0 + m + d])
        down = 1.0 - m - d
        fractions = (np.arange(GRID) + 0.5) / GRID  # midpoints of (0, 1): uniform mixture
        lam_worse = t / (1.0 + m) * fractions
        lam_not_worse = t / (down if down > 0 else m + d) * fractions
        return cls(m, d, a, None if max_episodes is None else int(max_episodes),
                   worse_table=np.log1p(np.outer(lam_worse, y_worse)),
                   not_worse_table=np.log1p(np.outer(lam_not_worse, y_not_worse)),
                   log_threshold=math.log(1.0 / a))

    def log_capitals(self, counts: Any) -> tuple[Any, Any]:
        """(log K for "worse", log K' for "not worse") at these (losses, ties, wins) counts."""
        return (_log_capital(counts, self.worse_table),
                _log_capital(counts, self.not_worse_table))


def _log_capital(counts: Any, table: np.ndarray) -> Any:
    """log of the grid-mixture capital after (losses, ties, wins) = counts[..., 0:3].

    A fixed stake's capital depends only on the counts, so the mixture is recomputed from them:
    log mean_j prod_i (1 + lam_j * y_i), a log-sum-exp over the grid. Works on one count triple
    or on a (rows, 3) array alike, with the same elementwise arithmetic.
    """
    c = np.asarray(counts, dtype=np.float64)
    logs = (c[..., 0, None] * table[:, 0] + c[..., 1, None] * table[:, 1]
            + c[..., 2, None] * table[:, 2])
    top = logs.max(axis=-1)
    return top + np.log(np.exp(logs - top[..., None]).mean(axis=-1))


def _hits(log_w: Any, log_nw: Any, log_threshold: float) -> tuple[Any, Any]:
    """Which capital crossed 1/alpha; if both did at once, the larger wins (ties: "worse").

    Each declaration still needs its own capital >= 1/alpha, so each error bound is untouched.
    """
    worse = np.logical_and(log_w >= log_threshold,
                           np.logical_or(log_w >= log_nw, log_nw < log_threshold))
    not_worse = np.logical_and(log_nw >= log_threshold, np.logical_not(worse))
    return worse, not_worse


def _outcome(value: Any, name: str) -> int:
    if isinstance(value, str) or value not in (0, 1):
        raise ValueError(f"{name} must be a success flag (True/False or 1/0), got {value!r}; "
                         f"e.g. update(a=True, b=False)")
    return int(value)


def _pts(fraction: float) -> str:
    return f"{100.0 * fraction:g}"


@dataclass(frozen=True)
class Verdict:
    """Where the test stopped, with the evidence behind it (JSON-ready via ``to_dict``)."""

    verdict: str  # "worse" | "not worse" | "undecided"
    episodes: int  # pairs used when it stopped
    statistic: dict
    margin: float
    indifference: float
    alpha: float

    def to_dict(self) -> dict:
        """Plain str/int/float only, so ``json.dumps`` takes it as is."""
        stat = {k: (int(v) if isinstance(v, numbers.Integral) else float(v))
                for k, v in self.statistic.items()}
        return {"verdict": str(self.verdict), "episodes": int(self.episodes),
                "statistic": stat, "margin": float(self.margin),
                "indifference": float(self.indifference), "alpha": float(self.alpha)}

    def line(self) -> str:
        """One line for the eval log: the verdict, the counts and the e-value that decided."""
        s, n = self.statistic, self.episodes
        thr = f"{s['threshold']:g} = 1/alpha"
        if self.verdict == WORSE:
            evidence = f"e-value {s['e_worse']:.1f} >= {thr}"
        elif self.verdict == NOT_WORSE:
            evidence = f"e-value {s['e_not_worse']:.1f} >= {thr}"
        else:
            evidence = (f"e-values worse {s['e_worse']:.3g}, not worse {s['e_not_worse']:.3g}, "
                        f"both < {thr}")
        counts = (f"new {s['new_successes']}/{n} vs reference "
                  f"{s['reference_successes']}/{n}")
        pts = f"margin {_pts(self.margin)} pts"
        if self.verdict != WORSE:
            pts += f", indifference {_pts(self.indifference)} pts"
        return (f"sequential verdict: {self.verdict} after {counted(n, 'paired episode')} "
                f"({counts}; {evidence}; {pts})")


class SequentialPairedTest:
    """Feed paired outcomes one seed at a time; it answers as soon as either capital hits 1/alpha.

    "worse" (new rate below the reference's by more than ``margin``) is wrong with probability
    <= alpha whenever delta >= -margin; "not worse" is wrong with probability <= alpha whenever
    delta <= -(margin + indifference). Both hold at any stopping time.
    """

    def __init__(self, margin: float = 0.0, indifference: float = 0.10, alpha: float = 0.05,
                 max_episodes: int | None = None) -> None:
        self._design = _Design.make(margin, indifference, alpha, max_episodes)
        self._n = 0
        self._counts = {"both": 0, "losses": 0, "wins": 0, "neither": 0}
        self._log_w = self._log_nw = 0.0
        self._final: Verdict | None = None

    @property
    def episodes(self) -> int:
        return self._n

    @property
    def finished(self) -> bool:
        """True once decided or at ``max_episodes``; further updates raise."""
        return self._final is not None

    def update(self, a: bool, b: bool) -> Verdict | None:
        """Add one seed (a = reference success, b = new success); the Verdict once it stops."""
        if self._final is not None:
            raise RuntimeError(f"the sequential test already stopped ({self._final.verdict} "
                               f"after {self._final.episodes} episodes); start a new "
                               "SequentialPairedTest for more pairs")
        ai, bi = _outcome(a, "a"), _outcome(b, "b")
        key = ("neither", "wins", "losses", "both")[2 * ai + bi]
        self._n += 1
        self._counts[key] += 1
        c = self._counts
        log_w, log_nw = self._design.log_capitals(
            [c["losses"], c["both"] + c["neither"], c["wins"]])
        self._log_w, self._log_nw = float(log_w), float(log_nw)
        worse, not_worse = map(bool, _hits(self._log_w, self._log_nw,
                                           self._design.log_threshold))
        cap = self._design.max_episodes
        if worse or not_worse or (cap is not None and self._n >= cap):
            self._final = self._make(WORSE if worse else NOT_WORSE if not_worse else UNDECIDED)
            return self._final
        return None

    def verdict(self) -> Verdict:
        """The final Verdict if stopped, else the current evidence as "undecided"."""
        return self._final if self._final is not None else self._make(UNDECIDED)

    def _make(self, verdict: str) -> Verdict:
        c, n, design = self._counts, self._n, self._design
        stat = {"e_worse": math.exp(self._log_w), "e_not_worse": math.exp(self._log_nw),
                "threshold": 1.0 / design.alpha, "losses": c["losses"], "wins": c["wins"],
                "ties": c["both"] + c["neither"],
                "delta_hat": (c["wins"] - c["losses"]) / n if n else 0.0,
                "new_successes": c["both"] + c["wins"],
                "reference_successes": c["both"] + c["losses"]}
        return Verdict(verdict, n, stat, design.margin, design.indifference, design.alpha)


def sequential_verdict(pairs: Iterable[tuple[bool, bool]], margin: float = 0.0,
                       indifference: float = 0.10, alpha: float = 0.05,
                       max_episodes: int | None = None) -> Verdict:
    """Run (reference, new) pairs in order and stop at the first decision (or when they run out)."""
    test = SequentialPairedTest(margin, indifference, alpha, max_episodes)
    for a, b in pairs:
        if (out := test.update(a, b)) is not None:
            return out
    return test.verdict()


def batch_verdicts(reference: Any, new: Any, margin: float = 0.0, indifference: float = 0.10,
                   alpha: float = 0.05, max_episodes: int | None = None,
                   truncation: float = TRUNCATION) -> tuple[np.ndarray, np.ndarray]:
    """The test on many paired sequences at once (rows of two equal-shape 0/1 arrays).

    Same arithmetic as ``update``, vectorised over rows, so error rates and stopping times can
    be simulated on thousands of sequences in well under a second. Returns (verdict strings,
    episodes used) per row. ``truncation`` (the largest stake as a fraction of the largest safe
    one) is there to simulate other designs; ``eval --against`` always uses ``TRUNCATION``.
    """
    a, b = np.asarray(reference), np.asarray(new)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(f"reference and new must be 2-D arrays of the same shape (rows = "
                         f"sequences, columns = seeds), got {a.shape} and {b.shape}; e.g. "
                         "np.zeros((2000, 400), bool) for both")
    if not (np.isin(a, (0, 1)).all() and np.isin(b, (0, 1)).all()):
        raise ValueError("reference and new must hold success flags (0/1 or bool) only; "
                         "e.g. rng.random((2000, 400)) < 0.9")
    design = _Design.make(margin, indifference, alpha, max_episodes, truncation)
    rows, cols = a.shape
    limit = cols if design.max_episodes is None else min(cols, design.max_episodes)
    # running (losses, ties, wins) per row after each seed
    d = b.astype(np.int64) - a.astype(np.int64)
    counts = np.cumsum(np.stack([d == -1, d == 0, d == 1], axis=-1)[:, :limit], axis=1)
    verdicts = np.full(rows, UNDECIDED, dtype="<U9")
    episodes = np.full(rows, limit, dtype=np.int64)
    active = np.ones(rows, dtype=bool)
    for t in range(limit):
        if not active.any():
            break
        log_w, log_nw = design.log_capitals(counts[:, t])
        worse, not_worse = _hits(log_w, log_nw, design.log_threshold)
        for hit, label in ((worse & active, WORSE), (not_worse & active, NOT_WORSE)):
            verdicts[hit] = label
            episodes[hit] = t + 1
        active &= ~(worse | not_worse)
    return verdicts, episodes


def fixed_n_for_power(delta_alt: float, margin: float, alpha: float, power: float,
                      p_discordant: float) -> int:
    """Episodes a fixed-size one-sided paired test needs to call "worse" with this power.

    Normal approximation on the mean paired difference (McNemar style), discordance held at
    ``p_discordant`` under both the null boundary delta = -margin (variance p - margin^2) and
    the alternative (variance p - delta_alt^2). Only the baseline the sequential test is
    compared with; the sequential test itself uses no approximation.
    """
    if not 0 <= margin < 1:
        raise ValueError(f"margin must be a fraction in [0, 1), got {margin!r}; e.g. 0.05")
    if not -1 <= delta_alt < -margin:
        raise ValueError(f"delta_alt must lie in [-1, -margin) = [-1, {-margin:g}) to be "
                         f"detectable as worse, got {delta_alt!r}; e.g. delta_alt=-0.10")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}; e.g. alpha=0.05")
    if not 0 < power < 1:
        raise ValueError(f"power must be in (0, 1), got {power!r}; e.g. power=0.8")
    if not max(-delta_alt, margin) <= p_discordant <= 1:
        raise ValueError(f"p_discordant must lie in [max(|delta_alt|, margin), 1] = "
                         f"[{max(-delta_alt, margin):g}, 1], got {p_discordant!r}; "
                         "e.g. p_discordant=0.18")
    z = NormalDist()
    sd0 = math.sqrt(p_discordant - margin * margin)
    sd1 = math.sqrt(max(p_discordant - delta_alt * delta_alt, 0.0))
    n = ((z.inv_cdf(1 - alpha) * sd0 + z.inv_cdf(power) * sd1) / (-margin - delta_alt)) ** 2
    return max(1, math.ceil(n - 1e-9))
