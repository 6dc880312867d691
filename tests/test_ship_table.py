"""ship_table.py (benchmarks/baselines): the shipping rule on real `so101-sim compare` output."""

from __future__ import annotations

from pathlib import Path

import pytest
from eval_folders import write_eval_run
from script_loader import load_script

from so101_sim.cli import main

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "baselines" / "ship_table.py"


SHIP_TABLE = load_script(SCRIPT)
TASKS = SHIP_TABLE.shipped_tasks(SHIP_TABLE.SHIPPED)


def _eval(folder: Path, task: str, name: str, ok: list[bool]) -> Path:
    return write_eval_run(folder, dict(zip(range(100_000, 100_000 + len(ok)), ok, strict=True)),
                          name=name, task=task)


def _ship_dir(root: Path, candidate: dict[str, int]) -> Path:
    """A ship_check.sh OUT_DIR: per task, 100 seeds the shipped policy solves 60 of; the
    candidate gains (positive) or loses (negative) that many seeds, with no others changing."""
    out = root / "ship"
    for task, delta in candidate.items():
        shipped = [i < 60 for i in range(100)]
        cand = [i < 60 + delta for i in range(100)]
        a = _eval(out / "eval" / task, task, "cand", cand)
        b = _eval(out / "shipped" / task, task, "shipped", shipped)
        assert main(["compare", str(a), str(b), "--out", str(out / "compare" / task)]) == 0
    return out


@pytest.mark.parametrize("deltas, verdict", [
    ({"stack": 15}, "ship: measurably better on stack, worse on none"),
    ({"stack": 15, "tidy": -15}, "do not ship: measurably worse on tidy"),
    ({"stack": 3}, "do not ship: nothing measurable on any task"),
])
def test_ship_rule(tmp_path, capsys, deltas, verdict):
    out = _ship_dir(tmp_path, {t: deltas.get(t, 0) for t in TASKS})
    capsys.readouterr()
    assert SHIP_TABLE.main([str(out)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith(verdict)
    rows = {line.split(" | ")[0][2:]: line for line in lines[2:-1]}
    assert set(rows) == set(TASKS)
    assert "| 60/100 |" in rows["lift"] and "| same |" in rows["lift"]
    if "stack" in deltas:
        n = 60 + deltas["stack"]
        assert rows["stack"].split(" | ")[1].startswith(f"{n}/100 = {n:.1f}%")


def test_missing_tasks_leave_it_undecided(tmp_path, capsys):
    out = _ship_dir(tmp_path, {"pick_place": 20})
    capsys.readouterr()
    SHIP_TABLE.main([str(out)])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("undecided: not evaluated yet on lift, pick_place_anywhere, "
                           "pick_place_dr, stack, tidy")


def test_the_tasks_are_the_shipped_cards():
    assert TASKS == ["lift", "pick_place", "pick_place_anywhere", "pick_place_dr", "stack",
                     "tidy"]


def test_a_folder_without_comparisons_is_one_line(tmp_path):
    with pytest.raises(SystemExit) as exc:
        SHIP_TABLE.main([str(tmp_path)])
    assert "no compare/<task>/compare.json" in str(exc.value) and "ship_check.sh" in str(exc.value)
