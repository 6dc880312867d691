"""grasp_trace.py (benchmarks/baselines): the gripper's first close, replayed from a real
``--save-rollouts`` dataset of the scripted expert (real env, rendering and video at 48x64)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "baselines" / "grasp_trace.py"
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HF_HUB_OFFLINE": "1"}


def _trace(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True,
                          timeout=120, env=ENV)


def test_the_experts_grasp_closes_on_the_cube_and_opens_to_release(tmp_path: Path) -> None:
    rollouts = tmp_path / "rollouts"
    run = subprocess.run(
        [sys.executable, "-m", "so101_sim.cli", "eval", "--policy", "expert", "--task",
         "pick_place", "--episodes", "1", "--n-envs", "1", "--image-size", "48x64",
         "--out", str(tmp_path / "eval"), "--save-rollouts", str(rollouts)],
        capture_output=True, text=True, timeout=300, env=ENV)
    assert run.returncode == 0, run.stderr
    out = _trace(str(rollouts))
    assert out.returncode == 0, out.stderr
    header, _, row = out.stdout.splitlines()
    cells = dict(zip([c.strip() for c in header.split("|")[1:-1]],
                     [c.strip() for c in row.split("|")[1:-1]], strict=True))
    assert cells["seed"] == "100000"
    assert cells["failure"] == "None" and cells["replay_matches"] == "True"
    assert int(cells["first_close"]) > 0
    # The expert closes with its default 4 mm clearance: the pads reach the cube, and the
    # cube has been carried to the pad by the end; the release opens the gripper again.
    assert float(cells["nearest_before_cm"]) < 1.0
    assert float(cells["cube_moved_cm"]) > 2.0
    assert int(cells["most_open_after"]) > 30
    # The expert's rollout against the expert on its seed: the same pan at the close.
    pans = _trace("--expert-pan", str(rollouts))
    assert pans.returncode == 0, pans.stderr
    header, _, row = pans.stdout.splitlines()
    cells = dict(zip([c.strip() for c in header.split("|")[1:-1]],
                     [c.strip() for c in row.split("|")[1:-1]], strict=True))
    assert cells["pan_at_close"] == cells["expert_pan_at_close"] != "None", cells
    # Every close: one, on the cube, held between the jaws (both pads on it, the joint
    # stopped open by the cube's width), and the cube rose with the tool.
    closes = _trace("--every-close", str(rollouts))
    assert closes.returncode == 0, closes.stderr
    header, _, *rows = closes.stdout.splitlines()
    assert len(rows) == 1, closes.stdout
    cells = dict(zip([c.strip() for c in header.split("|")[1:-1]],
                     [c.strip() for c in rows[0].split("|")[1:-1]], strict=True))
    assert cells["seed"] == "100000" and cells["cube"] == "0"
    assert all(float(d) <= 0.2 for d in cells["pads_at_rise_cm"].split("/")), cells
    assert int(cells["gripper_deg_at_rise"]) > 0, cells
    assert float(cells["tool_rose_cm"]) > 2.0, cells
    assert abs(float(cells["cube_rose_cm"]) - float(cells["tool_rose_cm"])) < 1.0, cells
    # One reopening after a close (the release), no retry.
    counts = _trace("--count-reopens", str(rollouts))
    assert counts.returncode == 0, counts.stderr
    assert counts.stdout.strip() == f"{rollouts}: 1 episode; by reopens after a close: 1: 1"


def test_a_folder_that_is_not_a_rollouts_dataset_is_named(tmp_path: Path) -> None:
    out = _trace(str(tmp_path))
    assert out.returncode != 0
    assert str(tmp_path) in out.stderr and "--save-rollouts" in out.stderr
    assert out.stdout == ""
