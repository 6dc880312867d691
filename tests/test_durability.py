"""A hard kill loses no finished work.

`so101-sim record` is killed with SIGKILL at several points (mid-episode, inside
save_episode, between finalize and the checkpoint, right after the checkpoint, and at an
arbitrary moment with its whole process group); `--resume` must then end with a dataset that
lerobot loads offline, holding the same episodes as a run that was never killed, with no
temporary folders left. A torn last line of eval's episodes.jsonl is dropped on resume.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from dataset_columns import columns_by_seed

from so101_sim.cli import main
from so101_sim.dataset import DEFAULT_REPO_ID, stored_seeds
from so101_sim.dataset.store import CRASH_ENV, SCRATCH, SPOOL
from so101_sim.harness.results import EpisodeRecord, RunDir
from so101_sim.record import record

SMALL = (48, 64)
N = 4
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HF_HUB_OFFLINE": "1"}


def _cli(out: Path, workers: int, *extra: str) -> list[str]:
    return [sys.executable, "-m", "so101_sim.cli", "record", "--episodes", str(N), "--out",
            str(out), "--image-size", "48x64", "--workers", str(workers),
            "--checkpoint-every", "2", *extra]


def _columns(root: Path) -> dict[int, dict[str, np.ndarray]]:
    return columns_by_seed(root, ("action", "observation.state", "frame_index"))


def _load(root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(DEFAULT_REPO_ID, root=root)


def _last_frames(ds) -> np.ndarray:
    last = ds[len(ds) - 1]
    return np.stack([last[f"observation.images.{c}"].numpy() for c in ("front", "side")])


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ref") / "ds"
    record(root, N, image_size=SMALL, progress=False)
    return root


def _group_gone(pgid: int, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.2)
    return False


def _total_episodes(root: Path) -> int:
    try:
        return json.loads((root / "meta" / "info.json").read_text())["total_episodes"]
    except (OSError, ValueError, KeyError):
        return 0


@pytest.mark.parametrize(("point", "workers", "min_reused"), [
    ("spooled:1", 1, 1),  # the first episode spooled, the next one mid-simulation
    ("save_episode:2", 2, 2),  # inside lerobot's save_episode: parquet written, videos not
    ("finalize:1", 1, 2),  # dataset finalized, checkpoint not yet recorded
    ("checkpoint:1", 2, 0),  # checkpoint recorded, spool not yet cleaned, writer not reopened
    ("timed", 2, 0),  # the whole process group, at whatever moment episode 3 is saved
], ids=["mid-episode", "in-save_episode", "after-finalize", "after-checkpoint", "group-kill"])
def test_sigkill_then_resume_keeps_every_episode(reference: Path, tmp_path: Path, point: str,
                                                 workers: int, min_reused: int, child_tmpdir: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "ds"
    env = {**ENV, "TMPDIR": child_tmpdir}
    if point != "timed":
        env[CRASH_ENV] = point
    proc = subprocess.Popen(_cli(root, workers), env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    if point == "timed":
        deadline = time.monotonic() + 300
        while _total_episodes(root) < 3 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGKILL)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == -signal.SIGKILL, err.decode()[-3000:]
    # A parent killed alone leaves no worker behind: they exit when its pipe closes.
    assert _group_gone(proc.pid, 120), "recording workers outlived their killed parent"

    # The resume runs in this process: only the killed run needs a process of its own (and
    # this one has torch and lerobot imported already, which a new one takes ~10 CPU-s to do).
    capsys.readouterr()
    assert main(_cli(root, workers, "--resume")[3:]) == 0
    said = capsys.readouterr().out
    reused = int(said.split(" recovered")[0].rsplit("; ", 1)[-1]) \
        if "recovered from before a kill" in said else 0
    assert reused >= min_reused, said

    ds = _load(root)
    assert ds.num_episodes == N and stored_seeds(root) == list(range(N))
    a, b = _columns(reference), _columns(root)
    for seed in range(N):
        for col in a[seed]:
            assert np.array_equal(a[seed][col], b[seed][col]), (seed, col)
    assert np.array_equal(_last_frames(ds), _last_frames(_load(reference)))
    leftovers = [p.name for p in root.iterdir() if p.name in (SPOOL, SCRATCH)
                 or p.name.startswith("tmp") or p.name.endswith(".tmp")]
    assert not leftovers, leftovers
    side = json.loads((root / "so101_sim_recording.json").read_text())
    assert side["tried"] == list(range(N))


def test_resume_of_an_unchanged_dataset_is_a_no_op(reference: Path, tmp_path: Path) -> None:
    """Recovery of a dataset that was never killed changes nothing and re-runs nothing."""
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(reference, root)
    before = {p: p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}
    s = record(root, N, image_size=SMALL, progress=False, resume=True)
    assert s["new_episodes"] == 0 and s["tried"] == 0
    assert _load(root).num_episodes == N
    after = {p: p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}
    data = [p for p in before if "data" in p.parts or "videos" in p.parts]
    assert all(before[p] == after[p] for p in data)


def test_torn_last_line_of_episodes_jsonl_is_dropped(tmp_path: Path) -> None:
    run = RunDir(tmp_path / "run")
    run.prepare({"policy": "p"}, resume=False)
    for seed in (1, 2, 3):
        run.append(EpisodeRecord(seed=seed, episode_ix=seed, success=True))
    text = run.episodes_path.read_text()
    run.episodes_path.write_text(text + text.splitlines()[0][:17])  # killed mid-write
    done = run.prepare({"policy": "p"}, resume=True)
    assert sorted(done) == [1, 2, 3]
    run.append(EpisodeRecord(seed=4, episode_ix=4, success=True))
    lines = run.episodes_path.read_text().splitlines()
    assert [json.loads(x)["seed"] for x in lines] == [1, 2, 3, 4]
    assert sorted(run.done()) == [1, 2, 3, 4]


def test_a_resume_whose_fingerprint_alone_differs_names_the_flags_it_hashes(tmp_path) -> None:
    """`eval --resume --n-action-steps 4` over an 8-step run said only that two hashes
    differ; the flags that change a fingerprint with the same checkpoint are now named."""
    run = RunDir(tmp_path / "run")
    first = {"policy": "p", "policy_fingerprint": "aaaa", "seed_start": 100000}
    run.prepare(first, resume=False)
    with pytest.raises(ValueError) as caught:
        run.prepare({**first, "policy_fingerprint": "bbbb"}, resume=True)
    assert ("policy_fingerprint: 'aaaa' there, 'bbbb' now (the same checkpoint name with other "
            "weights, or other inference flags: --n-action-steps, ") in str(caught.value)
    with pytest.raises(ValueError) as caught:  # another policy as well: its name says it
        run.prepare({**first, "policy": "q", "policy_fingerprint": "bbbb"}, resume=True)
    assert "inference flags" not in str(caught.value)
    assert "policy: 'p' there, 'q' now; policy_fingerprint" in str(caught.value)


def test_resume_after_a_kill_before_the_dataset_existed(tmp_path: Path) -> None:
    """Killed inside LeRobotDataset.create: only an empty meta/ is there; --resume starts."""
    root = tmp_path / "ds"
    (root / "meta").mkdir(parents=True)
    s = record(root, 1, image_size=SMALL, progress=False, resume=True)
    assert s["episodes"] == 1 and _load(root).num_episodes == 1
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("not a dataset")
    with pytest.raises(ValueError, match=r"is not a LeRobot dataset \(no meta/info.json\)"):
        record(tmp_path / "other", 1, image_size=SMALL, progress=False, resume=True)
    assert (tmp_path / "other" / "notes.txt").exists()
    # without --resume the refusal used to advise --resume, which then failed as above
    with pytest.raises(ValueError, match=r"other holds other files and no LeRobot dataset "
                                         r"\(no meta/info.json\), so --resume cannot continue "
                                         r"it either; .* choose another --out"):
        record(tmp_path / "other", 1, image_size=SMALL, progress=False)
    assert [p.name for p in (tmp_path / "other").iterdir()] == ["notes.txt"]
    with pytest.raises(ValueError, match="ds already exists and is not empty; pass --resume"):
        record(root, 2, image_size=SMALL, progress=False)  # a dataset: --resume is the fix
