"""bench_against's seed windows (step 5): each window gets its own reference and full weakened
run, on its own seeds; the medians are over the windows and the drop is pooled over all seeds."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from script_loader import load_script

BENCH = load_script(Path(__file__).resolve().parents[1] / "benchmarks" / "bench_against.py")


def _fake_runs(monkeypatch, walls: list[float]) -> list[list[str]]:
    """`run` that writes what each eval would: outcomes for a full run (the reference succeeds
    on every seed, the weakened one on even seeds), a verdict for an --against run."""
    ran: list[list[str]] = []
    left = iter(walls)

    def fake_run(cmd: list[str]) -> float:
        ran.append(cmd)
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True)
        weak = "weak" in cmd[cmd.index("--policy") + 1]
        if "--against" in cmd:
            (out / "eval_info.json").write_text(json.dumps({"sequential_verdict": {
                "verdict": "worse" if weak else "not worse", "episodes": 60}}))
            return next(left)
        start = int(cmd[cmd.index("--seed-start") + 1])
        policy = Path(cmd[cmd.index("--policy") + 1])
        (out / "eval_info.json").write_text(json.dumps({"config": {
            "policy_weights": f"weights of {policy.name}"}}))
        (out / "episodes.jsonl").write_text("".join(
            json.dumps({"seed": s, "success": not weak or s % 2 == 0, "status": "ok"}) + "\n"
            for s in range(start, start + 4)))
        return 99.0

    monkeypatch.setattr(BENCH, "run", fake_run)
    monkeypatch.setattr(BENCH, "weights_of", lambda policy: f"weights of {policy.name}")
    monkeypatch.setattr(BENCH, "outcomes", lambda folder: {
        (r := json.loads(line))["seed"]: r["success"]
        for line in (folder / "episodes.jsonl").read_text().splitlines()})
    return ran


def test_each_window_runs_on_its_own_seeds_and_the_median_is_over_windows(
        tmp_path: Path, monkeypatch, capsys) -> None:
    ran = _fake_runs(monkeypatch, [50.0, 30.0, 70.0, 40.0])
    rows = {"weakened": ([45.0, 65.0, 55.0], [90] * 3, ["worse"] * 3),
            "itself": ([35.0], [57], ["not worse"])}
    first = ({s: True for s in range(100000, 100004)}, {s: False for s in range(100000, 100004)})
    BENCH.other_windows(tmp_path, Path("ckpt"), Path("weak"), 2, 4, rows, first)

    full = [(c[c.index("--policy") + 1], c[c.index("--seed-start") + 1])
            for c in ran if "--against" not in c]
    assert full == [("ckpt", "100004"), ("weak", "100004"), ("ckpt", "100008"),
                    ("weak", "100008")]
    against = [c[c.index("--against") + 1] for c in ran if "--against" in c]
    assert against == [str(tmp_path / f"reference_{s}") for s in
                       ("100004", "100004", "100008", "100008")]
    out = capsys.readouterr().out
    # 12 seeds: the reference wins all; the weakened one none of the first 4, then 2 of 4 twice
    assert "pooled over 12 seeds: reference 12, weakened 4: +66.7 points" in out
    assert "4000 random 4-seed draws from the 12 pooled pairs, weakened: verdicts" in out
    # weakened: step 3's median 55.0, then 50.0 and 70.0 -> 55.0; itself: 35, 30, 40 -> 35
    assert ("3 windows, weakened: verdicts {'worse': 3}; wall median 55.0 s (55.0, 50.0, 70.0)"
            in out)
    assert "3 windows, itself: verdicts {'not worse': 3}; wall median 35.0 s" in out

    # windows follow the reference's seeds, wherever it starts
    ran = _fake_runs(monkeypatch, [50.0, 30.0])
    shifted = ({s: True for s in range(100200, 100204)}, {s: True for s in range(100200, 100204)})
    BENCH.other_windows(tmp_path / "b", Path("ckpt"), Path("weak"), 1, 4, rows, shifted)
    assert {c[c.index("--seed-start") + 1] for c in ran if "--against" not in c} == {"100204"}

    # a second call reuses the full runs already made
    ran = _fake_runs(monkeypatch, [50.0, 30.0, 70.0, 40.0])
    BENCH.other_windows(tmp_path, Path("ckpt"), Path("weak"), 2, 4, rows, first)
    assert len(ran) == 4 and all("--against" in c for c in ran)


def test_a_full_run_of_other_weights_in_out_is_refused_not_reused(tmp_path: Path, monkeypatch
                                                                  ) -> None:
    """Another --noise into the same --out: its weakened checkpoint has other weights, so the
    windows' full runs of the first noise must not be paired with it."""
    rows = {"weakened": ([45.0], [90], ["worse"]), "itself": ([35.0], [57], ["not worse"])}
    first = ({s: True for s in range(100000, 100004)}, {s: False for s in range(100000, 100004)})
    _fake_runs(monkeypatch, [50.0, 30.0])
    BENCH.other_windows(tmp_path, Path("ckpt"), Path("weak_noise0.014"), 1, 4, rows, first)
    ran = _fake_runs(monkeypatch, [50.0, 30.0])
    with pytest.raises(SystemExit, match=r"weak_full_100004 holds a run of weights weights of "
                       r"weak_noise0.014, not weak_noise0.02's \(weights of weak_noise0.02\)"):
        BENCH.other_windows(tmp_path, Path("ckpt"), Path("weak_noise0.02"), 1, 4, rows, first)
    assert ran == []  # the reference of the same checkpoint was reused, nothing else ran
