"""`so101-sim eval --save-rollouts DIR`: every evaluated episode as a LeRobotDataset.

Real env workers, rendering and encoding at 48x64. The policy is the scripted expert, made to
fail on chosen seeds by asking the gripper for 1000 (its limit is 100: the env clips it, the
gripper never closes), so a run has successes, failures and clipped actions. Checked: the
dataset loads in lerobot offline, one episode per seed in seed order, outcome columns equal
episodes.jsonl, ``action`` is what the env executed (clipped, and re-simulates exactly), the
outcomes do not change with the flag, and SIGTERM / SIGKILL + ``--resume`` end with every
seed exactly once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from collections import defaultdict
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from so101_sim.cli import main
from so101_sim.dataset import stored_seeds
from so101_sim.dataset.store import CRASH_ENV, SCRATCH, SPOOL, Spool, read_sidecar
from so101_sim.harness import evaluate, expert_policy
from so101_sim.harness.rollouts import DEFAULT_REPO_ID
from so101_sim.record import replay, replay_versions

sys.path.insert(0, str(Path(__file__).parent))
from tiny_policy import short_task

SEEDS = [100000, 100001, 100002]
STUCK = {100001}
KEYS = ("seed", "success", "failure_mode", "steps", "sum_reward", "actions_sha")
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HF_HUB_OFFLINE": "1"}


class _Stuck:
    """The expert, except on `stuck` seeds (gripper target 1000, clipped to 100: it stays
    open and the episode fails). `kill_at`: SIGTERM this process when that seed first asks.
    With no stuck seed it is the expert, and says so (a run of it resumes one of "expert")."""

    def __init__(self, task: str, stuck=frozenset(STUCK), kill_at: int | None = None) -> None:
        self.inner = expert_policy(task)
        self.info = self.inner.info if not stuck else dataclasses.replace(
            self.inner.info, name="stuck", fingerprint="stuck-v1")
        self.stuck, self.kill_at = stuck, kill_at
        self.emitted: dict[int, list[np.ndarray]] = defaultdict(list)

    def start_episode(self, slot: int, seed: int) -> None:
        self.inner.start_episode(slot, seed)
        self.emitted[seed] = []

    def predict_chunks(self, requests):
        if self.kill_at is not None and any(r.seed == self.kill_at for r in requests):
            self.kill_at = None
            os.kill(os.getpid(), signal.SIGTERM)  # eval turns it into KeyboardInterrupt
            time.sleep(5)
        actions = np.array(self.inner.predict_chunks(requests))
        for j, r in enumerate(requests):
            if r.seed in self.stuck:
                actions[j, :, 5] = 1000.0
            self.emitted[r.seed].extend(actions[j])
        return actions


def _quiet(**kw):
    return {"progress": False, "log": lambda _: None, "report": False, "videos": 0,
            "image_size": (48, 64), **kw}


def _outcomes(result: dict) -> list[tuple]:
    return [tuple(e[k] for k in KEYS) for e in result["per_episode"]]


def _dataset(root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(DEFAULT_REPO_ID, root=root)


def _episodes(root: Path) -> dict[int, dict[str, np.ndarray]]:
    """{seed: {column: values}} from the data parquet files."""
    import pandas as pd
    import pyarrow.parquet as pq

    df = pd.concat([pq.read_table(f).to_pandas() for f in sorted(root.glob("data/**/*.parquet"))])
    out = {}
    for _, ep in df.sort_values("index").groupby("episode_index"):
        seed = int(ep["episode_seed"].iloc[0])
        out[seed] = {c: np.stack([np.asarray(v) for v in ep[c]]) for c in ep.columns}
    return out


def _check_against_jsonl(root: Path, out: Path, seeds: list[int]) -> dict:
    """The dataset holds every seed once, in order, with the outcomes episodes.jsonl has."""
    ds = _dataset(root)
    assert ds.num_episodes == len(seeds) and stored_seeds(root) == seeds
    lines = [json.loads(x) for x in (out / "episodes.jsonl").read_text().splitlines()]
    last = {x["seed"]: x for x in lines if x["status"] == "ok"}
    eps = _episodes(root)
    for seed in seeds:
        ep, rec = eps[seed], last[seed]
        assert len(ep["action"]) == rec["steps"], seed
        assert set(ep["episode_success"].tolist()) == {rec["success"]}, seed
        assert set(ep["episode_failure_mode"].tolist()) == {rec["failure_mode"] or ""}, seed
        assert ep["next.done"][-1] and not ep["next.done"][:-1].any(), seed
        assert bool(ep["next.success"][-1]) == rec["success"], seed
        assert (ep["episode_seed"] == seed).all() and (np.diff(ep["frame_index"]) == 1).all()
    leftovers = [p.name for p in root.iterdir() if p.name in (SPOOL, SCRATCH)
                 or p.name.startswith("tmp") or p.name.endswith(".tmp")]
    assert not leftovers, leftovers
    return eps


def _sha(actions: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(actions, np.float32).tobytes()).hexdigest()[:16]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same policy and seeds evaluated without and with --save-rollouts."""
    base = tmp_path_factory.mktemp("rollouts")
    plain = evaluate(_Stuck("pick_place"), episodes=len(SEEDS), n_envs=2,
                     out_dir=base / "plain", **_quiet())
    policy = _Stuck("pick_place")
    saved = evaluate(policy, episodes=len(SEEDS), n_envs=2, out_dir=base / "saved",
                     save_rollouts=base / "ds", **_quiet())
    return {"plain": plain, "saved": saved, "policy": policy, "base": base}


def test_rollout_dataset_holds_every_episode_as_executed(runs):
    base, policy = runs["base"], runs["policy"]
    root = base / "ds"
    ds = _dataset(root)
    assert ds.fps == 30
    frame = ds[0]
    for cam in ("front", "side"):
        assert frame[f"observation.images.{cam}"].shape == (3, 48, 64)  # the render size
        assert tuple(ds.meta.features[f"observation.images.{cam}"]["shape"]) == (48, 64, 3)
    assert frame["task"] == "Pick up the red cube and place it on the green target."
    eps = _check_against_jsonl(root, base / "saved", SEEDS)
    outcome = {e["seed"]: e for e in runs["saved"]["per_episode"]}
    assert [outcome[s]["success"] for s in SEEDS] == [True, False, True]

    from so101_sim.sim import PickPlaceEnv

    env = PickPlaceEnv(obs_type="state")
    low, high = env.action_low, env.action_high
    env.close()
    for k, seed in enumerate(SEEDS):
        emitted = np.stack(policy.emitted[seed])
        assert np.array_equal(eps[seed]["action"], np.clip(emitted, low, high).astype(np.float32))
        if seed in STUCK:  # the policy asked for 1000, the env executed its limit
            assert (emitted[:, 5] == 1000).all() and (eps[seed]["action"][:, 5] == 100).all()
        else:
            assert _sha(eps[seed]["action"]) == outcome[seed]["actions_sha"]
        assert replay(root, k) == 0.0  # seed + stored actions re-simulate the stored states
    assert read_sidecar(root)["mujoco"] == metadata.version("mujoco")
    assert replay_versions(root) == ""  # recorded and replayed with this MuJoCo


def test_training_reads_the_rollout_dataset(runs):
    """lerobot's loader (windows, as lerobot-train asks) and so101-sim train's reader."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from so101_sim.train.demos import load_demos
    from so101_sim.train.presets import load_preset

    root = runs["base"] / "ds"
    ds = LeRobotDataset(DEFAULT_REPO_ID, root=root, delta_timestamps={
        "observation.images.front": [-1 / 30, 0], "observation.state": [-1 / 30, 0],
        "action": [i / 30 for i in range(-1, 15)]})
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=4)))
    assert batch["observation.images.front"].shape == (4, 2, 3, 48, 64)
    assert batch["action"].shape == (4, 16, 6) and len(batch["episode_failure_mode"]) == 4
    demos = load_demos(_dataset(root), load_preset("seed"), runs["base"] / "cache")
    assert demos.action.shape == (len(ds), 6)


def test_a_policy_trained_on_rollouts_is_not_measured_on_their_seeds(runs, capsys):
    """Rollouts are on evaluation seeds: train records them and says so, and eval refuses to
    measure the trained policy on them unless asked to (tests/test_trained_on.py: the rules)."""
    from tiny_presets import tiny_preset

    from so101_sim.train import read_train_info, train

    root, base = runs["base"] / "ds", runs["base"]
    r = train(root, base / "run", preset_name=str(tiny_preset(base)), steps=1, progress=False)
    info = read_train_info(r.pretrained_dir)
    assert info["dataset_eval_seeds"] == [[100000, 100002]] and info["dataset_task"] == "pick_place"
    out = capsys.readouterr().out
    assert f"{root} holds episodes on evaluation seeds (100000..100002)" in out
    # the failed seed (100001, episode 1) is named, with lerobot's command that drops it
    note = next(line for line in out.splitlines() if "failed (episode_success false" in line)
    assert note.startswith(f"so101-sim train: note: 1 of 3 episodes in {root} failed")
    command = shlex.split(note.split("to train on the successes only: ", 1)[1])
    assert command[0] == "lerobot-edit-dataset" and command[-1] == "[1]"
    exe = str(Path(sys.executable).parent / command[0])
    proc = subprocess.run([exe, *command[1:]], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert stored_seeds(Path(f"{root}_ok")) == [100000, 100002]
    with pytest.raises(ValueError, match=r"seeds 100001\.\.100002 of pick_place are among the "
                                         r"policy's training episodes .*--seed-start 100003"):
        evaluate(str(r.pretrained_dir), episodes=4, seed_start=100001, out_dir=base / "e",
                 **_quiet())
    assert not (base / "e").exists()  # refused before anything ran


def test_outcomes_do_not_depend_on_save_rollouts(runs):
    assert _outcomes(runs["saved"]) == _outcomes(runs["plain"])
    assert runs["saved"]["config"]["save_rollouts"] == str((runs["base"] / "ds").resolve())
    assert "save_rollouts" not in runs["plain"]["config"]


def test_resume_needs_the_same_rollouts_folder(runs, tmp_path, capsys):
    base = runs["base"]
    policy = _Stuck("pick_place")
    kw = {"episodes": len(SEEDS), "resume": True, **_quiet()}
    with pytest.raises(ValueError, match=r"that run saves its rollouts to .*ds; resume with "
                                         r"--save-rollouts"):
        evaluate(policy, out_dir=base / "saved", save_rollouts=tmp_path / "other", **kw)
    with pytest.raises(ValueError, match="without --save-rollouts: that run saves its rollouts"):
        evaluate(policy, out_dir=base / "saved", **kw)
    with pytest.raises(ValueError, match="was started without --save-rollouts"):
        evaluate(policy, out_dir=base / "plain", save_rollouts=tmp_path / "new", **kw)
    with pytest.raises(ValueError, match=r"is not this run's rollout dataset \(eval_out"):
        evaluate(policy, out_dir=tmp_path / "fresh", save_rollouts=base / "ds", **kw)
    assert not (tmp_path / "fresh").exists(), "a refused run leaves no folder behind"
    code = main(["eval", "--policy", "expert", "--episodes", "1", "--out", str(tmp_path / "x"),
                 "--save-rollouts", str(base / "ds")])
    assert code == 2
    err = capsys.readouterr().err
    assert f"--save-rollouts {base / 'ds'} already exists and is not empty" in err
    assert "choose another --save-rollouts" in err
    assert _dataset(base / "ds").num_episodes == len(SEEDS)  # untouched


def test_sigkill_sigterm_then_resume_records_every_seed_once(tmp_path, child_tmpdir):
    """Killed between an episode's spool and its episodes.jsonl line, then (resumed) inside
    lerobot's save_episode, then SIGTERM: each ends with a dataset --resume can finish, and
    the last --resume ends with every seed once, as episodes.jsonl has them."""
    task = str(short_task(tmp_path, max_steps=30))
    seeds = list(range(100000, 100005))
    out, root = tmp_path / "run", tmp_path / "ds"
    args = {"task": task, "episodes": len(seeds), "n_envs": 2, "out_dir": str(out),
            "save_rollouts": str(root), "checkpoint_every": 2, "progress": False,
            "report": False, "videos": 0, "image_size": (48, 64)}
    for point, resume in (("rollout_spooled:2", False), ("save_episode:2", True)):
        code = ("from so101_sim.harness import evaluate\n"
                f"evaluate('expert', resume={resume}, **{args!r})\n")
        proc = subprocess.run([sys.executable, "-c", code],
                              env={**ENV, CRASH_ENV: point, "TMPDIR": child_tmpdir},
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
        if not resume:  # two episodes spooled, the second one's line never written
            assert len(Spool(root).seeds()) == 2
            assert len((out / "episodes.jsonl").read_text().splitlines()) == 1
    kw = {**args, "log": lambda _: None}
    with pytest.raises(KeyboardInterrupt):
        evaluate(_Stuck(task, stuck=(), kill_at=seeds[-1]), resume=True, **kw)
    n = _dataset(root).num_episodes  # finalized at the interruption: it loads
    assert 2 <= n < len(seeds) and stored_seeds(root) == seeds[:n]
    assert main(["eval", "--policy", "expert", "--task", task, "--episodes", "5",
                 "--n-envs", "2", "--videos", "0", "--image-size", "48x64", "--out", str(out),
                 "--save-rollouts", str(root), "--resume"]) == 0
    eps = _check_against_jsonl(root, out, seeds)
    info = json.loads((out / "eval_info.json").read_text())
    for e in info["per_episode"]:
        assert _sha(eps[e["seed"]]["action"]) == e["actions_sha"]
