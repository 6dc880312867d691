"""The pick_place_dr analyses of benchmarks/baselines: by_place.py --factors and dr_groups.py."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from script_loader import load_script

from so101_sim.harness.stats import mcnemar_p_value

ROOT = Path(__file__).resolve().parents[1]
BASELINES = ROOT / "benchmarks" / "baselines"
CARD = ROOT / "policy" / "suite_diffusion"


def _by_place():
    return load_script(BASELINES / "by_place.py")


def _wins(path: Path) -> dict[int, bool]:
    return {e["seed"]: e["success"] for e in json.loads(path.read_text())["per_episode"]}


def test_factors_read_back_the_values_the_task_file_allows():
    by_place = _by_place()
    seeds = list(range(100000, 100012))
    values = by_place.factors("pick_place_dr", seeds)
    ranges = tomllib.loads((ROOT / "envs" / "pick_place_dr.toml").read_text())["randomize"]
    checks = {  # factor read from the model -> the task file's range, in the factor's unit
        "light intensity": ranges["light_intensity"],
        "ambient": ranges["ambient"],
        "light elevation (deg)": ranges["light_elevation"],
        "table pattern contrast": ranges["table_texture"],
        "cube size (mm)": [1000 * v for v in ranges["cube_size"]],
        "cube mass (g)": [1000 * v for v in ranges["cube_mass"]],
        "cube friction": ranges["cube_friction"],
        "servo gain factor": ranges["servo_gain"],
        "servo damping factor": ranges["servo_damping"],
        "distractors": ranges["distractors"],
        "front camera turn (deg)": [0.0, max(map(abs, ranges["camera_rotation"]))],
        "side camera fovy change (deg)": ranges["camera_fovy"],
    }
    for name, (lo, hi) in checks.items():
        v = values[name]
        assert len(v) == len(seeds)
        assert np.all((v >= lo - 1e-6) & (v <= hi + 1e-6)), (name, v, lo, hi)
        assert np.ptp(v) > 0, f"{name} did not vary over {len(seeds)} seeds"
    # the same seed draws the same scene: a second reading agrees exactly
    again = by_place.factors("pick_place_dr", seeds[:3])
    for name in checks:
        np.testing.assert_array_equal(again[name], values[name][:3])
    # a task without [randomize] has the bearing only
    assert list(by_place.factors("pick_place", seeds[:2])) == ["bearing (deg)"]


def test_bearing_of_each_cube_is_that_cubes_start_and_a_missing_cube_is_refused():
    import math

    import pytest

    from so101_sim.sim import PickPlaceEnv
    from so101_sim.tasks.layouts import PAN_AXIS_XY

    by_place = _by_place()
    seeds = [100000, 100001, 100002]
    env = PickPlaceEnv(task="tidy", obs_type="state")
    try:
        for k in range(3):
            want = []
            for s in seeds:
                env.reset(seed=s)
                x, y = env.cube_pos(k)[:2]
                want.append(math.degrees(math.atan2(y - PAN_AXIS_XY[1], x - PAN_AXIS_XY[0])))
            np.testing.assert_allclose(by_place.bearings("tidy", seeds, k), want)
    finally:
        env.close()
    # three cubes start in three places: the bins of one cube are not another's
    assert not np.allclose(by_place.bearings("tidy", seeds, 0), by_place.bearings("tidy", seeds, 2))
    with pytest.raises(SystemExit, match="--cube 1: task 'pick_place' has 1 cube"):
        by_place.bearings("pick_place", seeds, 1)


def test_failure_auc_is_one_half_without_association_and_one_when_failures_sit_above():
    by_place = _by_place()
    rng = np.random.default_rng(0)
    values = np.arange(40, dtype=float)
    failed = values >= 30
    auc, p = by_place.failure_auc(values, failed, rng, permutations=2000)
    assert auc == 1.0 and p < 0.001
    auc, p = by_place.failure_auc(values, ~failed, rng, permutations=2000)
    assert auc == 0.0 and p < 0.001
    alike = np.ones(40)  # one value for every seed: no order to find
    auc, p = by_place.failure_auc(alike, failed, rng, permutations=2000)
    assert auc == 0.5 and p == 1.0


def test_dr_groups_pairs_each_group_with_the_cards_seed_by_seed():
    out = subprocess.run([sys.executable, str(BASELINES / "dr_groups.py")], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    nominal = _wins(CARD / "eval_info_pick_place.json")
    full = _wins(CARD / "eval_info_pick_place_dr.json")
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")]
            for line in out.stdout.splitlines()[2:]}
    groups = [p.stem[3:] for p in sorted((BASELINES / "pick_place_dr").glob("dr_*.json"))]
    assert groups and all(g in rows for g in groups)
    for g in groups:
        run = _wins(BASELINES / "pick_place_dr" / f"dr_{g}.json")
        cells = rows[g]
        lost = sum(nominal[s] and not run[s] for s in run)
        won = sum(run[s] and not nominal[s] for s in run)
        kept = sum(run[s] and not full[s] for s in run)
        missed = sum(full[s] and not run[s] for s in run)
        assert cells[2].startswith(f"{sum(run.values())}/{len(run)} ")
        assert cells[4] == f"{lost} / {won}"
        assert cells[5] == f"{mcnemar_p_value(lost, won):.2g}"
        assert cells[6] == f"{kept} / {missed}"


def test_dr_groups_refuses_a_card_on_other_seeds(tmp_path):
    for task in ("pick_place", "pick_place_dr"):
        info = json.loads((CARD / f"eval_info_{task}.json").read_text())
        info["per_episode"] = info["per_episode"][:50]
        (tmp_path / f"eval_info_{task}.json").write_text(json.dumps(info))
    out = subprocess.run([sys.executable, str(BASELINES / "dr_groups.py"), "--card",
                          str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert out.returncode != 0
    assert "are not the card's" in out.stderr and "dr_" in out.stderr


def test_by_place_names_a_missing_file(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=r"gone/eval_info\.json: no such file; pass an "):
        _by_place().main([str(tmp_path / "gone" / "eval_info.json")])
