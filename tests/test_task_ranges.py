"""Task files whose cube or target cannot be solved are refused when they load.

Ranges must lie on the table, clear of the robot's base and inside the reach the scripted
expert solves top-down; the numbers behind the check (``tasks.workspace``) must match the
scene files and the built model, and every task file of the suite must still load.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from so101_sim.tasks import TaskSpecError, available_tasks, load_task
from so101_sim.tasks.layouts import PAN_AXIS_XY
from so101_sim.tasks.workspace import BASE_X, BASE_Y, PAN_LIMIT, REACH, TABLE_X, TABLE_Y
from so101_sim.utils.paths import assets_dir, envs_dir


def _write(tmp_path: Path, base: str, *edits: tuple[str, str]) -> Path:
    text = (envs_dir() / f"{base}.toml").read_text()
    for pattern, new in edits:
        text, n = re.subn(pattern, new, text, count=1, flags=re.M)
        assert n == 1, pattern
    path = tmp_path / "task.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(("base", "edits", "message"), [
    ("pick_place", [(r"^x = \[0\.17, 0\.25\]", "x = [3.0, 3.1]")],
     r"cube.x = \[3, 3.1\] is off the table; expected within \[-0.232, 0.632\] m"),
    ("pick_place", [(r"^x = \[0\.17, 0\.25\]", "x = [0.6, 0.6]")],
     r"cube.x = \[0.6, 0.6\], cube.y = \[0.02, 0.12\] puts the cube 0.56.\.\.0.57. m from the "
     r"arm's pan axis .*expected every point within 0.1..0.27 m"),
    ("pick_place", [(r"^y = \[0\.02, 0\.12\]", "y = [0.02, 0.7]")],
     r"cube.y = \[0.02, 0.7\] is off the table"),
    ("pick_place", [(r"^x = \[0\.20, 0\.20\]", "x = [0.0, 0.02]"),
                    (r"^y = \[-0\.12, -0\.12\]", "y = [-0.01, 0.01]")],
     r"target.x = \[0, 0.02\], target.y = \[-0.01, 0.01\] overlaps the robot's base"),
    ("pick_place", [(r"^x = \[0\.17, 0\.25\]", "x = [-0.2, -0.1]")],
     r"cube.x = \[-0.2, -0.1\], cube.y = \[0.02, 0.12\] reaches 175 deg around the pan "
     r"axis; the arm turns at most 110 deg"),
    ("pick_place_anywhere", [(r"^reach = \[0\.13, 0\.26\]", "reach = [0.13, 0.40]")],
     r"layout.reach = \[0.13, 0.4\] is invalid; expected within \[0.1, 0.27\] m"),
    ("pick_place_anywhere", [(r"^x = \[0\.10, 0\.29\]", "x = [0.45, 0.5]")],
     r"cube.x = \[0.45, 0.5\], .* never within layout.reach = \[0.13, 0.26\]"),
])
def test_unsolvable_ranges_are_refused(tmp_path: Path, base: str, edits: list, message: str):
    with pytest.raises(TaskSpecError, match=message):
        load_task(_write(tmp_path, base, *edits))


def test_every_task_of_the_suite_still_loads() -> None:
    for name in available_tasks():
        load_task(name)
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    import shelf_kind  # noqa: F401  (registers the example kind of docs/architecture.md)

    load_task(Path(__file__).parent / "shelf.toml")


def test_the_numbers_match_the_scene_files_and_the_model() -> None:
    scene = ET.parse(assets_dir() / "scene_pick_place.xml").getroot()
    table = scene.find(".//geom[@name='table']")
    (cx, cy, _), (hx, hy, _) = (tuple(map(float, table.get(k).split())) for k in ("pos", "size"))
    assert (cx - hx, cx + hx) == pytest.approx(TABLE_X) and (cy - hy, cy + hy) == \
        pytest.approx(TABLE_Y)
    robot = ET.parse(assets_dir() / "so101.xml").getroot()
    plate = robot.find(".//geom[@name='base_plate']")
    (px, py, _), (sx, sy, _) = (tuple(map(float, plate.get(k).split())) for k in ("pos", "size"))
    assert (px - sx, px + sx) == pytest.approx(BASE_X) and (py - sy, py + sy) == \
        pytest.approx(BASE_Y)
    pan = robot.find(".//joint[@name='shoulder_pan']")
    assert float(pan.get("range").split()[1]) == pytest.approx(PAN_LIMIT)
    shoulder = robot.find(".//body[@name='shoulder']")
    assert float(shoulder.get("pos").split()[0]) == pytest.approx(PAN_AXIS_XY[0])

    from so101_sim.sim import SO101Env
    from so101_sim.sim.reset_options import workspace

    env = SO101Env("pick_place", obs_type="state")
    try:  # the same table and base that reset(options=...) checks against
        ws = workspace(env.model)
    finally:
        env.close()
    assert ws.x == pytest.approx(TABLE_X) and ws.y == pytest.approx(TABLE_Y)
    assert ws.base_x == pytest.approx(BASE_X) and ws.base_y == pytest.approx(BASE_Y)


def test_the_expert_reaches_the_far_edge_of_the_reach() -> None:
    """Top-down IK at grasp height hits the target at REACH[1] all around the pan range."""
    from so101_sim.expert.kinematics import TopDownIK
    from so101_sim.sim import SO101Env

    env = SO101Env("pick_place", obs_type="state")
    try:
        ik = TopDownIK(env.model)
        seed = np.deg2rad([0.0, 0.0, 0.0, 90.0, 0.0])
        for angle in np.linspace(-1.5, 1.5, 5):
            for r in REACH:
                p = np.array([PAN_AXIS_XY[0] + r * math.cos(angle), r * math.sin(angle),
                              0.0145])
                err = min(ik.solve(p, angle + k * math.pi / 2, seed)[1] for k in range(4))
                assert err < 1e-3, (r, angle, err)
    finally:
        env.close()


@pytest.mark.parametrize(("variant", "parent"), [
    ("lift_right", "lift"),
    ("pick_place_anywhere_right", "pick_place_anywhere"),
    ("pick_place_anywhere_corner", "pick_place_anywhere"),
])
def test_the_extra_demo_variants_draw_inside_their_task(variant: str, parent: str) -> None:
    """benchmarks/baselines/tasks/ variants record extra demos for a region of their task: they
    must be that task with a narrower cube range, so their demos are the task's own."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "baselines" / "tasks"
    var, task = load_task(path / f"{variant}.toml"), load_task(parent)
    assert var.kind == task.kind and var.description == task.description
    assert var.reach == task.reach and var.max_steps == task.max_steps
    assert var.cube_yaw == task.cube_yaw and var.cube_size == task.cube_size
    for mine, theirs in ((var.cube_x, task.cube_x), (var.cube_y, task.cube_y)):
        assert theirs[0] <= mine[0] <= mine[1] <= theirs[1], (variant, mine, theirs)
    assert (var.target_x, var.target_y) == (task.target_x, task.target_y)
