"""Success-rate statistics and the `so101_sim.testing` regression helper, plus the project's
expert regression test built on it."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from so101_sim.harness import PolicyInfo, StepPolicy
from so101_sim.harness.stats import (
    binom_cdf,
    critical_successes,
    episodes_needed,
    p_value_below,
    power_below,
    wilson_interval,
)
from so101_sim.testing import assert_success_rate, check_success_rate, curtailed_verdict

sys.path.insert(0, str(Path(__file__).parent))
from tiny_policy import short_task

#: The expert solved 500/500 seeds; the lower end of that Wilson interval is the baseline, so
#: the baseline's own uncertainty cannot fail CI.
EXPERT_BASELINE = round(wilson_interval(500, 500)[0], 3)  # 0.992


def test_wilson_interval_known_values():
    lo, hi = wilson_interval(500, 500)
    assert hi == 1.0 and lo == pytest.approx(0.99238, abs=1e-4)
    lo, hi = wilson_interval(25, 50)
    assert (lo, hi) == pytest.approx((0.3664, 0.6336), abs=1e-4)
    assert wilson_interval(0, 10)[0] == 0.0


def test_binomial_tail_matches_brute_force():
    for n, p in ((10, 0.5), (37, 0.9), (200, 0.95)):
        for k in (0, n // 3, n - 3, n):
            exact = sum(math.comb(n, i) * p ** i * (1 - p) ** (n - i) for i in range(k + 1))
            assert binom_cdf(k, n, p) == pytest.approx(exact, rel=1e-9, abs=1e-300)
    assert p_value_below(18, 20, 0.992) == pytest.approx(1 - 0.992 ** 20 - 20 * 0.008
                                                         * 0.992 ** 19, rel=1e-9)


def test_episodes_needed_reaches_power_and_is_minimal():
    n = episodes_needed(0.95, 0.85, alpha=0.01, power=0.8)
    assert n == 82
    assert power_below(n, 0.95, 0.85, 0.01) >= 0.8
    assert all(power_below(m, 0.95, 0.85, 0.01) < 0.8 for m in range(1, n))
    k = critical_successes(n, 0.95, 0.01)
    assert binom_cdf(k, n, 0.95) <= 0.01 < binom_cdf(k + 1, n, 0.95)


def test_check_success_rate_fails_only_on_significant_drops():
    assert check_success_rate(47, 50, 0.95).passed  # 94%: noise
    assert check_success_rate(44, 50, 0.95).passed  # 88%: p = 0.038, not below alpha 0.01
    drop = check_success_rate(40, 50, 0.95)
    assert not drop.passed and drop.p_value < 0.01
    assert "SIGNIFICANTLY BELOW BASELINE" in drop.line() and "Wilson" in drop.line()
    with pytest.raises(ValueError, match="as a fraction"):
        check_success_rate(40, 50, 95)


def test_curtailed_verdict_is_the_full_tests_verdict_whatever_the_rest_give():
    """Stopping early never changes the verdict: for every prefix (successes in `ran` of n), a
    decided prefix gets the verdict every completion gets, and an undecided one has
    completions on both sides (so it stops at the first episode that settles it)."""
    for n, baseline in ((20, 0.7), (24, 0.805), (40, 0.24)):
        for ran in range(1, n + 1):
            for k in range(ran + 1):
                full = {check_success_rate(k + extra, n, baseline).passed
                        for extra in range(n - ran + 1)}
                verdict = curtailed_verdict(k, ran, n, baseline, 0.01)
                if verdict is None:
                    assert full == {True, False}
                else:
                    assert full == {verdict == "pass"}
                    early = check_success_rate(k, n, baseline, ran=ran)
                    assert early.passed == (verdict == "pass") and early.episodes_run == ran
    assert curtailed_verdict(97, 97, 100, 0.992, 0.01) == "pass"  # 3 failures left can't fail it
    assert curtailed_verdict(96, 100 - 4, 100, 0.992, 0.01) is None
    with pytest.raises(ValueError, match="do not decide"):
        check_success_rate(5, 20, 0.7, ran=12)


class _HoldStill:
    def reset(self, seed):
        pass

    def select_action(self, obs):
        return np.asarray(obs["agent_pos"], dtype=np.float32)


def _hold_still() -> StepPolicy:
    return StepPolicy(_HoldStill, PolicyInfo(name="hold-still", fingerprint="hold-still"))


def test_assert_success_rate_fails_a_policy_that_never_succeeds(tmp_path, capsys):
    policy = _hold_still()
    with pytest.raises(pytest.fail.Exception, match="success rate regression"):
        assert_success_rate(policy, baseline=0.9, episodes=4, n_envs=2,
                            task=str(short_task(tmp_path, max_steps=8)))
    # 0 of 3 already fails the 4-episode test (at most 1/4 vs 0.9), so the fourth never runs
    assert "success 0/3 = 0.0%" in (out := capsys.readouterr().out)
    assert "decided after 3 of 4 episodes" in out


def test_a_baseline_no_outcome_can_fail_passes_after_one_episode(tmp_path):
    """0 of 3 is not significantly below 1% at alpha 0.01, so the verdict is known before any
    episode; the check still runs one, so that it reports on something measured."""
    policy = _hold_still()
    check = assert_success_rate(policy, baseline=0.01, episodes=3, n_envs=1,
                                task=str(short_task(tmp_path, max_steps=8)))
    assert check.passed and check.episodes_run == 1


def test_expert_success_rate_regression():
    """The project's regression test for the scripted expert (state observations, no
    rendering). 100 episodes at alpha 0.01 against 0.992 fail at 4 or more failures; they
    catch a drop to 95% with power 0.74 and to 90% with power 0.99 (and stop once 97
    succeed)."""
    check = assert_success_rate("expert", baseline=EXPERT_BASELINE, episodes=100, n_envs=2)
    assert check.n == 100 and 97 <= check.episodes_run <= 100
