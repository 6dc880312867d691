"""pair_with_card.py (benchmarks/baselines): pairing a look seed by seed, on committed looks."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from so101_sim.harness.stats import mcnemar_p_value

BASELINES = Path(__file__).resolve().parents[1] / "benchmarks" / "baselines"
SCRIPT = BASELINES / "pair_with_card.py"
LOOK = "act_suite3_te_step_0010000.json"
EARLIER = "act_suite_te_step_0010000.json"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True,
                          timeout=60)


def _wins(path: Path) -> dict[int, bool]:
    return {e["seed"]: e["success"] for e in json.loads(path.read_text())["per_episode"]}


def test_against_an_earlier_look_counts_the_discordant_seeds_of_both_files():
    out = _run(LOOK, "--against", EARLIER)
    assert out.returncode == 0, out.stderr
    rows = {line.split("|")[1].strip(): line for line in out.stdout.splitlines()[2:]}
    assert len(rows) == 6
    for task, line in rows.items():
        a, b = _wins(BASELINES / task / LOOK), _wins(BASELINES / task / EARLIER)
        seeds = sorted(set(a) & set(b))
        only_a = sum(a[s] and not b[s] for s in seeds)
        only_b = sum(b[s] and not a[s] for s in seeds)
        cells = [c.strip() for c in line.split("|")]
        assert cells[2].startswith(f"{sum(a[s] for s in seeds)}/{len(seeds)} ")
        assert cells[4] == f"{sum(b[s] for s in seeds)}/{len(seeds)}"
        assert cells[5] == f"{only_a} / {only_b}"
        assert float(cells[6]) == float(f"{mcnemar_p_value(only_a, only_b):.2g}")


def test_against_a_missing_look_names_it_and_prints_no_table():
    out = _run(LOOK, "--against", "no_such_look.json")
    assert out.returncode != 0
    assert "no_such_look.json" in out.stderr and "expected a look's eval_info.json" in out.stderr
    assert out.stdout == ""


def test_an_unknown_look_is_named_not_an_empty_table():
    out = _run("no_such_look.json")
    assert out.returncode == 1 and out.stdout == ""
    assert out.stderr.startswith("no_such_look.json: no such file in any task's folder here")
