"""The anytime-valid sequential paired test: error rates, power and speed, and the API.

Error rates and stopping times are simulated on thousands of synthetic paired sequences with a
seeded numpy RNG, through ``batch_verdicts`` (checked here to agree with the one-pair-at-a-time
``SequentialPairedTest``). Run with ``-s`` to see the measured numbers.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from so101_sim.harness.sequential import (
    NOT_WORSE,
    TRUNCATION,
    UNDECIDED,
    WORSE,
    SequentialPairedTest,
    Verdict,
    batch_verdicts,
    fixed_n_for_power,
    sequential_verdict,
)

ALPHA = 0.05
SIMS = 2000
HORIZON = 400


def paired(rng: np.random.Generator, sims: int, episodes: int, p_ref: float, p_new: float,
           rho: float) -> tuple[np.ndarray, np.ndarray]:
    """(reference, new) successes; with probability rho a seed is equally hard for both."""
    u = rng.random((sims, episodes))
    shared = rng.random((sims, episodes)) < rho
    v = np.where(shared, u, rng.random((sims, episodes)))
    return u < p_ref, v < p_new


def discordance(p_ref: float, p_new: float, rho: float) -> float:
    """P(a != b) for ``paired``: shared seeds disagree only between the two rates."""
    independent = p_ref * (1 - p_new) + (1 - p_ref) * p_new
    return rho * abs(p_ref - p_new) + (1 - rho) * independent


# (margin, reference rate, new rate, rho, the verdict that would be an error)
ERROR_CASES = [
    # margin 0: delta = 0 is the "worse" boundary; delta = -0.10 the "not worse" one
    (0.0, 0.9, 0.9, 0.5, WORSE),    # same policy, seed-correlated noise
    (0.0, 0.9, 0.9, 0.0, WORSE),    # same rate, independent noise (most discordance at 0.9)
    (0.0, 0.9, 0.9, 1.0, WORSE),    # identical outcomes
    (0.0, 0.5, 0.5, 0.0, WORSE),    # the highest-variance boundary: half the pairs disagree
    (0.0, 0.9, 0.8, 0.5, NOT_WORSE),
    (0.0, 0.9, 0.8, 0.0, NOT_WORSE),
    # margin 5 points: delta = -0.05 is the "worse" boundary; delta = -0.15 the other one
    (0.05, 0.9, 0.85, 0.5, WORSE),
    (0.05, 0.9, 0.85, 0.0, WORSE),
    (0.05, 0.5, 0.45, 0.0, WORSE),
    (0.05, 0.9, 0.9, 1.0, WORSE),   # no change at all, inside H
    (0.05, 0.9, 0.9, 0.0, WORSE),   # no change, independent noise
    (0.05, 0.9, 0.75, 0.5, NOT_WORSE),
    (0.05, 0.9, 0.75, 0.0, NOT_WORSE),
]


@pytest.mark.parametrize(("case", "margin", "p_ref", "p_new", "rho", "wrong"),
                         [(i, *c) for i, c in enumerate(ERROR_CASES)])
def test_error_rate_stays_below_alpha(case, margin, p_ref, p_new, rho, wrong):
    rng = np.random.default_rng([2024, case])
    a, b = paired(rng, SIMS, HORIZON, p_ref, p_new, rho)
    verdicts, episodes = batch_verdicts(a, b, margin=margin, alpha=ALPHA, max_episodes=HORIZON)
    rate = float(np.mean(verdicts == wrong))
    se = math.sqrt(ALPHA * (1 - ALPHA) / SIMS)
    print(f"\nmargin {margin:.2f} ref {p_ref} new {p_new} rho {rho}: false '{wrong}' "
          f"{rate:.4f} (alpha {ALPHA}, 3 SE {3 * se:.4f}), median episodes "
          f"{np.median(episodes):g}")
    assert rate <= ALPHA + 3 * se, f"false '{wrong}' rate {rate:.4f} > alpha + 3 SE"
    # Ville's bound is conservative (the capital overshoots 1/alpha when it crosses), so the
    # estimate itself sits below alpha, not merely within noise of it
    assert rate < ALPHA, f"false '{wrong}' rate {rate:.4f} not below alpha {ALPHA}"


def test_a_ten_point_regression_is_caught_sooner_than_a_fixed_size_test_of_equal_power():
    rng = np.random.default_rng(20230101)
    p_ref, p_new, rho, cap = 0.9, 0.8, 0.5, 200
    a, b = paired(rng, SIMS, cap, p_ref, p_new, rho)
    verdicts, episodes = batch_verdicts(a, b, margin=0.0, alpha=ALPHA, max_episodes=cap)
    power = float(np.mean(verdicts == WORSE))
    median = float(np.median(episodes))  # every run, undecided ones counted at the cap
    p_disc = discordance(p_ref, p_new, rho)
    # a fixed-size test with the power the sequential one reached within its cap
    fixed = fixed_n_for_power(p_new - p_ref, 0.0, ALPHA, min(power, 1 - 1 / SIMS), p_disc)
    fixed_80 = fixed_n_for_power(p_new - p_ref, 0.0, ALPHA, 0.8, p_disc)
    msg = (f"sequential: power {power:.3f} within {cap}, median {median:g} episodes, mean "
           f"{episodes.mean():.1f}; fixed-size test of the same power needs {fixed} "
           f"(of 80% power {fixed_80})")
    print("\n" + msg)
    assert power >= 0.8, msg
    assert median < fixed, msg
    assert float(np.mean(verdicts == NOT_WORSE)) <= ALPHA, msg


def test_a_policy_against_itself_is_cleared_early():
    rng = np.random.default_rng(7)
    a, _ = paired(rng, SIMS, HORIZON, 0.9, 0.9, 1.0)
    verdicts, episodes = batch_verdicts(a, a.copy(), alpha=ALPHA, max_episodes=HORIZON)
    msg = (f"identical outcomes: 'not worse' in {np.mean(verdicts == NOT_WORSE):.3f}, median "
           f"{np.median(episodes):g} episodes")
    print("\n" + msg)
    assert np.all(verdicts == NOT_WORSE), msg
    assert np.median(episodes) < 100, msg  # well under 200
    # the same policy re-run with seed-level noise (half the seeds shared)
    a, b = paired(rng, SIMS, HORIZON, 0.9, 0.9, 0.5)
    verdicts, episodes = batch_verdicts(a, b, alpha=ALPHA, max_episodes=HORIZON)
    msg = (f"noisy re-run: 'not worse' in {np.mean(verdicts == NOT_WORSE):.3f}, median "
           f"{np.median(episodes):g} episodes")
    print(msg)
    assert np.mean(verdicts == NOT_WORSE) >= 0.9, msg
    assert np.median(episodes) < 200, msg


def test_batch_agrees_with_one_pair_at_a_time():
    rng = np.random.default_rng(3)
    for margin, p_new in ((0.0, 0.8), (0.05, 0.9), (0.05, 0.75)):
        a, b = paired(rng, 40, 150, 0.9, p_new, 0.3)
        verdicts, episodes = batch_verdicts(a, b, margin=margin, max_episodes=150)
        for row in range(len(a)):
            one = sequential_verdict(zip(a[row], b[row], strict=True), margin=margin,
                                     max_episodes=150)
            assert (one.verdict, one.episodes) == (verdicts[row], episodes[row])
            if one.verdict == WORSE:
                assert one.statistic["e_worse"] >= 1 / ALPHA
            elif one.verdict == NOT_WORSE:
                assert one.statistic["e_not_worse"] >= 1 / ALPHA


@pytest.mark.parametrize("truncation", [0.5, 0.95])
def test_other_stake_caps_keep_the_error_bound_and_change_only_the_power(truncation):
    # validity needs only stakes that keep every factor positive, so any cap in (0, 1) holds
    # alpha; the cap moves how soon a real regression is called (benchmarks/against_limits.py)
    rng = np.random.default_rng([7, int(truncation * 100)])
    for p_new, wrong in ((0.9, WORSE), (0.8, NOT_WORSE)):  # each null's boundary, margin 0
        a, b = paired(rng, SIMS, HORIZON, 0.9, p_new, 0.5)
        verdicts, _ = batch_verdicts(a, b, truncation=truncation)
        assert float(np.mean(verdicts == wrong)) < ALPHA, (truncation, wrong)
    a, b = paired(rng, 500, HORIZON, 0.9, 0.75, 0.5)
    shipped, by_default = batch_verdicts(a, b), batch_verdicts(a, b, truncation=TRUNCATION)
    assert (shipped[0] == by_default[0]).all() and (shipped[1] == by_default[1]).all()
    timid = batch_verdicts(a, b, truncation=0.2)[1]
    assert np.median(timid) > np.median(shipped[1]), "a smaller cap should bet less, stop later"


@pytest.mark.parametrize("bad", [0, 1.0, 1.5, -0.2, "0.5", True])
def test_a_stake_cap_outside_0_1_is_refused_with_the_value(bad):
    a = np.ones((2, 5), dtype=bool)
    with pytest.raises(ValueError, match=rf"truncation must be .*got {bad!r}") as err:
        batch_verdicts(a, a, truncation=bad)
    assert "e.g. truncation=0.75" in str(err.value)


def test_fixed_n_baseline_has_its_power():
    # the normal-approximation baseline, checked against a simulated fixed-size z-test
    rng = np.random.default_rng(11)
    p_disc, delta = 0.18, -0.10
    n = fixed_n_for_power(delta, 0.0, ALPHA, 0.8, p_disc)
    p_loss, p_win = (p_disc - delta) / 2, (p_disc + delta) / 2
    d = rng.choice([-1, 0, 1], size=(20000, n), p=[p_loss, 1 - p_disc, p_win])
    z = d.mean(axis=1) * math.sqrt(n) / math.sqrt(p_disc)
    power = float(np.mean(z < -1.6448536269514722))
    assert abs(power - 0.8) < 0.03, (n, power)
    assert fixed_n_for_power(delta, 0.0, ALPHA, 0.9, p_disc) > n
    assert fixed_n_for_power(-0.15, 0.0, ALPHA, 0.8, p_disc) < n
    assert fixed_n_for_power(delta, 0.05, ALPHA, 0.8, p_disc) > n
    with pytest.raises(ValueError, match="delta_alt"):
        fixed_n_for_power(-0.05, 0.05, ALPHA, 0.8, p_disc)
    with pytest.raises(ValueError, match="p_discordant"):
        fixed_n_for_power(delta, 0.0, ALPHA, 0.8, 0.05)


def test_update_after_a_decision_raises():
    test = SequentialPairedTest()
    result = None
    for _ in range(500):
        result = test.update(True, False)  # the new policy fails every seed the old one passed
        if result is not None:
            break
    assert isinstance(result, Verdict)
    assert result.verdict == WORSE and test.finished
    assert test.verdict() == result
    with pytest.raises(RuntimeError, match="already stopped"):
        test.update(True, True)


def test_max_episodes_gives_undecided():
    # alternating wins and losses: no evidence either way
    pairs = [(True, False), (False, True)] * 50
    test = SequentialPairedTest(max_episodes=20)
    results = [test.update(a, b) for a, b in pairs[:20]]
    assert results[:-1] == [None] * 19
    assert results[-1].verdict == UNDECIDED and results[-1].episodes == 20
    with pytest.raises(RuntimeError):
        test.update(True, True)
    assert sequential_verdict(pairs, max_episodes=30).episodes == 30
    ran_out = sequential_verdict(pairs[:12])
    assert (ran_out.verdict, ran_out.episodes) == (UNDECIDED, 12)
    fresh = SequentialPairedTest().verdict()
    assert (fresh.verdict, fresh.episodes, fresh.statistic["delta_hat"]) == (UNDECIDED, 0, 0.0)


@pytest.mark.parametrize(("kwargs", "named"), [
    ({"margin": -0.1}, "got -0.1"), ({"margin": 1.0}, "got 1.0"), ({"margin": "5"}, "got '5'"),
    ({"indifference": 0.0}, "got 0.0"), ({"indifference": float("nan")}, "got nan"),
    ({"margin": 0.99, "indifference": 1.5}, "indifference=1.5"),
    ({"alpha": 0.5}, "got 0.5"), ({"alpha": 0}, "got 0"), ({"max_episodes": 0}, "got 0"),
    ({"max_episodes": 2.5}, "got 2.5"), ({"max_episodes": True}, "got True"),
])
def test_bad_arguments_name_the_value(kwargs, named):
    with pytest.raises(ValueError, match=r"e\.g\. ") as err:
        SequentialPairedTest(**kwargs)
    name = next(iter(kwargs)) if len(kwargs) == 1 else "margin + indifference"
    assert f"{name} must be" in str(err.value) and named in str(err.value), str(err.value)
    assert " (eval --" in str(err.value)  # the flag a CLI user types, beside the keyword
    with pytest.raises(ValueError, match="success flag"):
        SequentialPairedTest().update(2, True)


def test_verdict_serialises_and_reads_as_one_line():
    verdict = sequential_verdict([(True, False)] * 30 + [(True, True)] * 30, margin=0.05)
    assert verdict.verdict == WORSE
    data = json.loads(json.dumps(verdict.to_dict(), allow_nan=False))
    assert data["verdict"] == WORSE and data["episodes"] == verdict.episodes
    assert data["statistic"]["losses"] == verdict.episodes
    assert data["statistic"]["threshold"] == pytest.approx(20.0)
    line = verdict.line()
    assert "\n" not in line
    assert f"worse after {verdict.episodes} paired episodes" in line
    assert f"new 0/{verdict.episodes} vs reference {verdict.episodes}/{verdict.episodes}" in line
    assert "margin 5 pts" in line
    cleared = sequential_verdict([(True, True)] * 200)
    assert cleared.verdict == NOT_WORSE
    assert f"not worse after {cleared.episodes} paired episodes" in cleared.line()
    undecided = sequential_verdict([(True, False), (False, True)], max_episodes=2)
    assert "undecided after 2 paired episodes" in undecided.line()
