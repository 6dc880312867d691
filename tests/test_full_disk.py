"""A full disk is one line, and nothing finished is lost.

Each test mounts a small tmpfs (root only: skipped elsewhere, with the reason), fills it to a
few hundred KB and runs a real command into it. The command must end with one line (no
traceback) that names what it was writing, the space left and the exact command that
continues; after freeing space, that command must finish the run with every seed.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from tiny_presets import tiny_preset

from so101_sim.cli import main
from so101_sim.dataset import stored_seeds
from so101_sim.record import record
from so101_sim.train.state import list_checkpoints, load_training_state

EXE = str(Path(sys.executable).parent / "so101-sim")
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HF_HUB_OFFLINE": "1"}
EVAL = ["eval", "--policy", "expert", "--n-envs", "2", "--image-size", "48x64"]
SEEDS = list(range(100_000, 100_006))


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    """A 3 MB tmpfs at tmp_path/disk (unmounted afterwards)."""
    path = tmp_path / "disk"
    path.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(path)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({(r.stderr or r.stdout).strip()}); the "
                    "full-disk tests need root (mount -t tmpfs)")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def _fill(disk: Path, keep_kb: int) -> Path:
    """Fill `disk` up to `keep_kb` KB free; deleting the returned file frees the space."""
    filler = disk / "filler.bin"
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    filler.write_bytes(b"\0" * max(0, free - keep_kb * 1024))
    return filler


def _cli(argv: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([EXE, *argv], env=ENV, capture_output=True, text=True,
                          timeout=timeout)


def _one_line(r: subprocess.CompletedProcess, command: str, what: str, folder: Path) -> str:
    """The failed run's message; returns the command it says continues the run."""
    assert r.returncode == 2, (r.returncode, r.stderr[-3000:])
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith(f"so101-sim {command}: ")]
    assert len(errors) == 1, r.stderr[-3000:]
    line = errors[0]
    assert f"the disk is full: writing {what} {folder}" in line, line
    assert "free there" in line and "then run: so101-sim " in line, line
    return line.split("then run: ", 1)[1]


def _again(command: str) -> int:
    """The command the message gave, run in this process (its imports are done; pytest shows
    what it printed if it fails): only the run that meets the full disk needs its own."""
    argv = shlex.split(command)
    assert argv[0] == "so101-sim" and "--resume" in argv
    return main(argv[1:])


@pytest.mark.parametrize("free_kb", [120, 400])  # the spool write; lerobot's video concatenation
def test_eval_save_rollouts_on_a_full_disk(disk: Path, tmp_path: Path, free_kb: int) -> None:
    filler = _fill(disk, free_kb)
    rollouts, out = disk / "rollouts", tmp_path / "out"
    r = _cli([*EVAL, "--episodes", str(len(SEEDS)), "--videos", "0", "--out", str(out),
              "--save-rollouts", str(rollouts)])
    command = _one_line(r, "eval", "the rollout dataset", rollouts)
    filler.unlink()
    assert _again(command) == 0
    assert stored_seeds(rollouts) == SEEDS
    info = json.loads((out / "eval_info.json").read_text())
    assert [e["seed"] for e in info["per_episode"]] == SEEDS


def test_eval_out_on_a_full_disk(disk: Path) -> None:
    filler = _fill(disk, 24)
    out = disk / "out"
    r = _cli([*EVAL, "--episodes", "4", "--videos", "4", "--out", str(out)])
    command = _one_line(r, "eval", "the evaluation", out)
    filler.unlink()
    assert _again(command) == 0
    info = json.loads((out / "eval_info.json").read_text())
    assert [e["seed"] for e in info["per_episode"]] == SEEDS[:4]
    assert len(list((out / "videos").glob("*.mp4"))) == 4


@pytest.mark.parametrize("free_kb", [100, 400])  # a worker's encoder; the parquet writer
def test_record_on_a_full_disk(disk: Path, free_kb: int) -> None:
    filler = _fill(disk, free_kb)
    out = disk / "ds"
    r = _cli(["record", "--episodes", "4", "--image-size", "48x64", "--out", str(out),
              "--checkpoint-every", "1"])
    command = _one_line(r, "record", "the dataset", out)
    filler.unlink()
    assert _again(command) == 0
    assert stored_seeds(out) == [0, 1, 2, 3]


def test_train_checkpoint_on_a_full_disk(disk: Path, tmp_path: Path) -> None:
    """The step-4 checkpoint does not fit: one line, step 2 stays the last checkpoint (and
    loads); with more space, --resume finishes the run."""
    record(tmp_path / "ds", 2, image_size=(48, 64), progress=False)
    tiny = tiny_preset(tmp_path)
    out = disk / "run"
    subprocess.run(["mount", "-o", "remount,size=300m", str(disk)], check=True)
    args = ["train", "--preset", str(tiny), "--dataset", str(tmp_path / "ds"), "--threads",
            "1", "--out", str(out)]
    assert main([*args, "--steps", "2"]) == 0
    r = _cli([*args, "--steps", "4", "--resume"])
    command = _one_line(r, "train", "the training run", out)
    assert [c.name for c in list_checkpoints(out)] == ["step_0000002"]
    assert load_training_state(list_checkpoints(out)[-1] / "training_state.pt", "cpu")[
        "step"] == 2
    assert not (out / "checkpoints" / "step_0000004").exists()  # the partial one is gone
    subprocess.run(["mount", "-o", "remount,size=800m", str(disk)], check=True)
    assert _again(command) == 0
    assert [c.name for c in list_checkpoints(out)] == ["step_0000002", "step_0000004"]
