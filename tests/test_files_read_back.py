"""Files are written whole or not at all, and files read back are checked, not trusted.

A failed write (a full disk, a kill) leaves the old file; a log's torn last line is dropped.
A hand-edited eval_info.json or episodes.jsonl (``"success": "no"``, a seed outside the run,
counts that disagree) is refused in one line naming the file and the key, instead of
counting as a success in ``so101-sim compare``.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest

from so101_sim.cli import main
from so101_sim.harness import evaluate
from so101_sim.harness.compare import compare_runs
from so101_sim.harness.results import RunDir
from so101_sim.utils.atomic import append_line, read_jsonl, write_atomic, write_json_atomic


def test_a_failed_write_leaves_the_old_file(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "eval_info.json"
    write_json_atomic(path, {"old": True})

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError, match="No space left"):
        write_atomic(path, b'{"new": tr')
    monkeypatch.undo()
    assert json.loads(path.read_text()) == {"old": True}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval_info.json"]  # no .tmp left


def test_a_torn_last_line_is_dropped_and_a_bad_one_named(tmp_path: Path) -> None:
    log = tmp_path / "log.jsonl"
    for step in (1, 2):
        append_line(log, json.dumps({"step": step}))
    with log.open("a") as f:
        f.write('{"step": 3, "lo')  # killed mid-write
    assert read_jsonl(log) == [{"step": 1}, {"step": 2}]
    log.write_text('{"step": 1}\nnot json\n{"step": 3}\n')
    with pytest.raises(ValueError, match=r"log.jsonl: line 2 is not JSON"):
        read_jsonl(log)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("runs")
    for name in ("a", "b"):
        evaluate("expert", episodes=2, n_envs=1, videos=0, out_dir=root / name,
                 progress=False, report=False, log=lambda _: None)
    return root


def _copy(runs: Path, tmp_path: Path, name: str = "a") -> Path:
    dest = tmp_path / name
    dest.mkdir()
    for f in (runs / name).iterdir():
        (dest / f.name).write_bytes(f.read_bytes())
    return dest


def _edit_info(run: Path, edit) -> None:
    info = json.loads((run / "eval_info.json").read_text())
    edit(info)
    (run / "eval_info.json").write_text(json.dumps(info))


@pytest.mark.parametrize(("edit", "message"), [
    (lambda i: i["per_episode"][0].update(success="no"),
     r"eval_info.json: per_episode\[0\].success = 'no' is invalid; expected true or false"),
    (lambda i: i["per_episode"][1].update(seed=7),
     r"per_episode\[1\].seed = 7 is invalid; expected a seed in 100000..100001"),
    (lambda i: i["per_episode"][1].update(seed=100_000),
     r"per_episode\[1\].seed = 100000 is invalid; expected each seed once"),
    (lambda i: i["aggregated"].update(n_success=0),
     r"aggregated.n_success = 0 is invalid; expected 2, as per_episode has it"),
    (lambda i: (i["per_episode"][0].update(success=False), i["aggregated"].update(n_success=1)),
     r"per_episode seed 100000 has success = False, but .*episodes.jsonl has True"),
])
def test_compare_refuses_a_hand_edited_eval_info(runs: Path, tmp_path: Path, capsys, edit,
                                                 message: str) -> None:
    a = _copy(runs, tmp_path)
    _edit_info(a, edit)
    with pytest.raises(ValueError, match=message):
        compare_runs(a, runs / "b")
    assert main(["compare", str(a), str(runs / "b"), "--out", str(tmp_path / "cmp")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "rerun the evaluation with its arguments plus --resume" in err[0]
    assert not (tmp_path / "cmp").exists()


def test_a_hand_edited_episodes_jsonl_is_named(runs: Path, tmp_path: Path, capsys) -> None:
    a = _copy(runs, tmp_path)
    lines = (a / "episodes.jsonl").read_text().splitlines()
    rec = json.loads(lines[1])
    rec["success"] = "no"
    (a / "episodes.jsonl").write_text("\n".join([lines[0], json.dumps(rec)]) + "\n")
    with pytest.raises(ValueError, match=r"episodes.jsonl line 2: success = 'no' is invalid; "
                                         r"expected true or false"):
        RunDir(a).done()
    with pytest.raises(ValueError, match=r"episodes.jsonl line 2: success = 'no'"):
        compare_runs(a, runs / "b")  # eval_info.json is checked against it
    assert main(["eval", "--policy", "expert", "--episodes", "2", "--n-envs", "1", "--videos",
                 "0", "--out", str(a), "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("so101-sim eval: error: ") and "line 2: success = 'no'" in err[-1]
