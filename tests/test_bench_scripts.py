"""The benchmark scripts' own mistakes are a user's first contact with them: bad arguments and a
failed child run end in one message that says what went wrong, never a bare traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from eval_folders import write_eval_run
from script_loader import load_script

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def test_bench_train_refuses_too_few_steps_to_time(monkeypatch, capsys) -> None:
    script = load_script(BENCH / "bench_train.py")
    monkeypatch.setattr(sys, "argv", ["bench_train.py", "--dataset", "d", "--steps", "2"])
    with pytest.raises(SystemExit) as exit_:
        script.main()
    assert exit_.value.code == 2
    assert "--steps 2 is too few" in capsys.readouterr().err


def test_bench_train_shows_why_the_trainer_failed(tmp_path: Path) -> None:
    script = load_script(BENCH / "bench_train.py")
    with pytest.raises(SystemExit, match=r"so101-sim train \(fp32\) failed:(.|\n)*"
                                         r"is not a LeRobotDataset folder"):
        script.run_ours(tmp_path / "no_dataset", "cpu", 4, 4, tmp_path)


def test_bench_env_jobs_without_a_job_prints_its_usage() -> None:
    proc = subprocess.run([sys.executable, str(BENCH / "bench_env_jobs.py"), "--help"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.startswith("usage: bench_env_jobs.py JOB_JSON")
    assert "Traceback" not in proc.stderr


def test_bench_record_makes_its_out_dir(tmp_path: Path) -> None:
    out_dir = tmp_path / "not" / "there"
    proc = subprocess.run([sys.executable, str(BENCH / "bench_record.py"), "--episodes", "1",
                           "--workers", "1", "--image-size", "48x64", "--out-dir", str(out_dir)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert out_dir.is_dir() and not any(out_dir.iterdir())  # its datasets were temporary
    assert "| 1 |" in proc.stdout  # the one-worker row of the table


def _eval_run(root: Path, name: str, seeds: range) -> Path:
    return write_eval_run(root / name, {s: s % 3 != 0 for s in seeds})


def test_ablation_table_says_which_runs_it_cannot_pair(tmp_path: Path, capsys) -> None:
    script = load_script(BENCH / "ablation_table.py")
    a = _eval_run(tmp_path, "a", range(100_000, 100_030))
    b = _eval_run(tmp_path, "b", range(100_000, 100_030))
    short = _eval_run(tmp_path, "short", range(100_000, 100_020))
    assert script.main([f"a={a}", f"b={b}"]) == 0
    assert "| b |" in capsys.readouterr().out
    assert script.main([f"a={a}", f"s={short}"]) == 2
    assert "ablation_table: error: cannot compare" in capsys.readouterr().err
    assert script.main([f"a={a}", f"gone={tmp_path / 'gone'}"]) == 2
    assert "does not exist" in capsys.readouterr().err
