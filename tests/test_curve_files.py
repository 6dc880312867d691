"""`benchmarks/baselines/curves.py --files`: a run's curve drawn from committed per-seed files,
for runs whose folder (and `eval_curve.jsonl`) is gone."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks" / "baselines"))

import curves  # noqa: E402

STACK = ROOT / "benchmarks" / "baselines" / "stack"
START = ROOT / "policy" / "suite_diffusion" / "eval_info_stack.json"


def test_files_make_one_row_each_with_its_step_and_a_plot(tmp_path, capsys) -> None:
    files = [f"{START}:0", str(STACK / "stack_ft2_step_0006425.json")]
    assert curves.main(["--name", "demo", "--idle-steps-per-s", "0.775", "--plots",
                        str(tmp_path), "--files", *files]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| `demo`")]
    want = [json.loads(Path(f.split(":")[0]).read_text())["aggregated"]["n_success"]
            for f in (str(START), files[1])]
    assert [r.split(" | ")[2] for r in rows] == ["0", "6425"]
    assert [r.split(" | ")[4] for r in rows] == [f"{k}/200" for k in want]
    assert rows[1].split(" | ")[3] == f"{6425 / 0.775 / 3600:.2f}"
    assert (tmp_path / "demo_stack.png").stat().st_size > 10_000


def test_a_file_without_a_step_is_refused_with_the_fix(tmp_path) -> None:
    with pytest.raises(SystemExit, match=r"give the step as .*:STEP"):
        curves.main(["--name", "demo", "--idle-steps-per-s", "0.775", "--plots", str(tmp_path),
                     "--files", str(START)])


def test_an_edited_file_is_refused_not_misread(tmp_path) -> None:
    info = json.loads(START.read_text())
    info["per_episode"][0]["success"] = "no"  # a string would count as a success if summed
    bad = tmp_path / "edited_step_0000100.json"
    bad.write_text(json.dumps(info))
    with pytest.raises(SystemExit, match=r"per_episode\[0\]\.success"):
        curves.main(["--name", "demo", "--idle-steps-per-s", "0.775", "--plots", str(tmp_path),
                     "--files", str(bad)])
