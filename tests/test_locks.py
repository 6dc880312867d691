"""Two runs, one folder: the second is refused in one line naming the folder and the holder.

Every command that writes a folder (eval --out, eval --save-rollouts, record, train, curve,
export, explain) holds an flock on a lock file in it. Two processes started together
(``SO101_SIM_LOCK_PAUSE_S`` makes the winner hold its lock a few seconds before it goes on, so
the two surely overlap): exactly one runs, the other exits 2 with one line. Every command run
while another process holds its folder exits 2 with that line and changes nothing in the
folder, and a SIGKILLed holder blocks nobody.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from tiny_presets import tiny_preset

from so101_sim.cli import main
from so101_sim.harness.curve import CURVE_LOCK
from so101_sim.harness.export import export_lock
from so101_sim.record import record
from so101_sim.train import train
from so101_sim.utils.locks import LOCK_FILE, PAUSE_ENV, FolderInUseError, FolderLock

SMALL = (48, 64)
EXE = str(Path(sys.executable).parent / "so101-sim")
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HF_HUB_OFFLINE": "1"}
EVAL = ["eval", "--policy", "expert", "--episodes", "2", "--n-envs", "1", "--videos", "0",
        "--image-size", "48x64"]


@pytest.fixture(scope="module")
def material(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A 2-episode dataset, a tiny preset and a 2-step training run (checkpoints for curve
    and export)."""
    root = tmp_path_factory.mktemp("locks")
    record(root / "ds", 2, image_size=SMALL, progress=False)
    tiny = tiny_preset(root)
    train(root / "ds", root / "run", preset_name=str(tiny), steps=2, threads=1,
          progress=False)
    ck = sorted((root / "run" / "checkpoints").glob("step_*"))[-1] / "pretrained_model"
    return {"ds": root / "ds", "tiny": tiny, "run": root / "run", "ck": ck}


def _commands(m: dict[str, Path], d: Path) -> dict[str, tuple[list[str], list[str], Path]]:
    """name -> (argv of run 1, argv of run 2, the folder they share)."""
    one = [*EVAL, "--out", str(d / "out")]
    rollouts = [*EVAL, "--save-rollouts", str(d / "rollouts")]
    train_args = ["train", "--preset", str(m["tiny"]), "--dataset", str(m["ds"]), "--steps",
                  "2", "--threads", "1", "--out", str(d / "run")]
    return {
        "eval --out": (one, one, d / "out"),
        "eval --save-rollouts": ([*rollouts, "--out", str(d / "a")],
                                 [*rollouts, "--out", str(d / "b")], d / "rollouts"),
        "record": (["record", "--episodes", "1", "--image-size", "48x64", "--out",
                    str(d / "ds")],) * 2 + (d / "ds",),
        "train": (train_args, train_args, d / "run"),
        "curve": (["curve", str(m["run"]), "--episodes", "1", "--n-envs", "1"],) * 2
        + (m["run"],),
        "export": (["export", str(m["ck"]), "--out", str(d / "export")],) * 2 + (d,),
        "explain": (["explain", "--dataset", str(m["ds"]), "--frame", "2", "--out",
                     str(d / "page")],) * 2 + (d / "page",),
    }


def _start(argv: list[str], env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen([EXE, *argv], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


COMMANDS = ["eval --out", "eval --save-rollouts", "record", "train", "curve", "export",
            "explain"]


# Two processes that start together race for the lock; the lock is the same `FolderLock` in
# every command, so the race runs for two of them, and every command is refused below.
@pytest.mark.parametrize("name", ["eval --out", "train"])
def test_two_runs_started_together_one_is_refused(material, tmp_path: Path, name: str) -> None:
    first, second, folder = _commands(material, tmp_path)[name]
    env = {**ENV, PAUSE_ENV: "6"}
    procs = [_start(first, env), _start(second, env)]
    outs = [p.communicate(timeout=600) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 2], (codes, [o[1][-2000:] for o in outs])
    loser = outs[[p.returncode for p in procs].index(2)]
    winner = procs[[p.returncode for p in procs].index(0)]
    last = loser[1].strip().splitlines()[-1]
    assert "is in use:" in last and f"pid {winner.pid} " in last, loser[1][-2000:]
    assert f"so101-sim {first[0]}" in last and str(folder) in last
    assert "Traceback" not in loser[1]
    assert not (folder / LOCK_FILE).exists()  # the winner removed its lock file on exit


def _snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file() and not p.name.endswith(".lock")}


def _hold(folder: Path, name: str = LOCK_FILE) -> subprocess.Popen:
    """Another process holding `folder`'s lock (as a writing run would)."""
    code = ("import sys, time; from so101_sim.utils.locks import FolderLock; "
            f"FolderLock({str(folder)!r}, 'the test', name={name!r}).acquire(); "
            "print('held', flush=True); time.sleep(600)")
    proc = subprocess.Popen([sys.executable, "-c", code], env=ENV, stdout=subprocess.PIPE,
                            text=True, start_new_session=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def _kill(proc: subprocess.Popen) -> None:
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=60)


@pytest.mark.parametrize("name", COMMANDS)
def test_a_refused_run_changes_nothing_in_the_folder(material, tmp_path: Path, name: str,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Each command, run in this process while another process holds its folder: exit 2, one
    line naming the holder, and not a byte changed in the folder."""
    # curve's lock is its own (a curve may run beside the training); export's is beside
    # the folder it replaces
    lock = export_lock(tmp_path / "export").name if name == "export" else LOCK_FILE
    if name == "curve":  # curve writes into the training run: refuse on a copy of it
        shutil.copytree(material["run"], tmp_path / "run_copy")
        material, lock = {**material, "run": tmp_path / "run_copy"}, CURVE_LOCK
    argv, _, folder = _commands(material, tmp_path)[name]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "notes.txt").write_text("someone else's")
    before, names = _snapshot(folder), set(os.listdir(folder))
    holder = _hold(folder, lock)
    capsys.readouterr()
    try:
        code = main(argv)
    finally:
        _kill(holder)
    err = capsys.readouterr().err
    assert code == 2, err[-2000:]
    last = err.strip().splitlines()[-1]
    assert f"is in use: pid {holder.pid} " in last and f"so101-sim {argv[0]}" in last, last
    assert str(folder) in last and "Traceback" not in err
    assert _snapshot(folder) == before
    assert set(os.listdir(folder)) == names | {lock}


def test_a_sigkilled_run_leaves_no_lock_behind(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ds"
    argv = ["record", "--episodes", "1", "--image-size", "48x64", "--out", str(out)]
    proc = _start(argv, {**ENV, PAUSE_ENV: "120"})
    deadline = time.monotonic() + 120
    while not (out / LOCK_FILE).is_file() or not (out / LOCK_FILE).read_text():
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.2)
    assert json.loads((out / LOCK_FILE).read_text())["pid"] == proc.pid
    _kill(proc)
    assert (out / LOCK_FILE).exists()  # the file stays, the kernel dropped its lock
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 0  # in this process: its imports are done
    assert ": 1 episode (" in capsys.readouterr().out and not (out / LOCK_FILE).exists()


def test_lock_in_one_process_names_its_holder(tmp_path: Path) -> None:
    holder = _hold(tmp_path / "x")
    try:
        with pytest.raises(FolderInUseError, match=rf"x is in use: pid {holder.pid} \(python"):
            FolderLock(tmp_path / "x", "the thing").acquire()
    finally:
        _kill(holder)
    with FolderLock(tmp_path / "x", "the thing"):  # free once its holder is gone
        assert (tmp_path / "x" / LOCK_FILE).is_file()
    assert not (tmp_path / "x" / LOCK_FILE).exists()
    with pytest.raises(RuntimeError, match="boom"), FolderLock(tmp_path / "new", "it"):
        raise RuntimeError("boom")
    assert not (tmp_path / "new").exists()  # created by a run that failed at once: removed


@pytest.mark.parametrize("argv", [["eval", "--policy", "expert", "--episodes", "1"],
                                  ["record", "--episodes", "1"]], ids=["eval", "record"])
def test_an_out_under_a_file_is_refused_in_one_line(argv, tmp_path: Path, capsys) -> None:
    # before, mkdir's NotADirectoryError came out as a traceback
    (tmp_path / "notes.txt").write_text("mine")
    out = tmp_path / "notes.txt" / "run"
    code = main([*argv, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"{out} lies under {tmp_path / 'notes.txt'}, a file; expected a folder for" in err
    assert (tmp_path / "notes.txt").read_text() == "mine"
