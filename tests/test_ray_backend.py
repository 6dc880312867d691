"""eval and record on the Ray backend, on a local Ray runtime (``ray.init(num_cpus=2)``).

The determinism contract across backends: the same seeds give the same per-episode results
with ``--backend local --n-envs 1`` and ``--backend ray --n-envs 3``; a killed actor's episode
is re-run; ``--resume`` works the same; ``record`` stores the same episodes. The two-node
cluster test is in test_ray_cluster.py.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from so101_sim.dataset import stored_seeds  # noqa: E402
from so101_sim.harness import evaluate  # noqa: E402
from so101_sim.record import record  # noqa: E402
from so101_sim.workers import start_pool  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
import test_workers  # noqa: E402
from dataset_columns import columns_by_seed  # noqa: E402
from tiny_policy import make_tiny_diffusion_checkpoint, short_task  # noqa: E402

SEEDS = 6
KEYS = ("seed", "success", "failure_mode", "steps", "sum_reward", "actions_sha")
SMALL = (48, 64)


def _outcomes(result: dict) -> list[tuple]:
    return [tuple(e[k] for k in KEYS) for e in result["per_episode"]]


def _quiet(**kw):
    return {"progress": False, "log": lambda _: None, "report": False, **kw}


@pytest.fixture(scope="module", autouse=True)
def ray_runtime():
    ray.init(address="local", num_cpus=2, include_dashboard=False,
             object_store_memory=200_000_000,
             logging_level="WARNING")
    ray.cloudpickle.register_pickle_by_value(test_workers)  # its service, for the actors
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def expert_local(tmp_path_factory) -> dict:
    return evaluate("expert", episodes=SEEDS, n_envs=1, videos=0,
                    out_dir=tmp_path_factory.mktemp("local") / "run", **_quiet())


def test_ray_pool_contract() -> None:
    with start_pool(test_workers.CounterFactory(10), 2, backend="ray",
                    name="test-counter") as pool:
        test_workers.check_pool_contract(pool)
        info = pool.info().to_dict()
        assert info["backend"] == "ray" and info["cpus_per_worker"] == 1.0


def test_expert_on_ray_matches_local(expert_local, tmp_path) -> None:
    res = evaluate("expert", episodes=SEEDS, n_envs=3, videos=1, backend="ray",
                   out_dir=tmp_path / "ray", **_quiet())
    assert _outcomes(res) == _outcomes(expert_local)
    assert res["config"]["workers"]["backend"] == "ray"
    assert res["config"]["workers"]["workers"] == 3
    video = tmp_path / "ray" / "videos" / "episode_0000_seed100000.mp4"
    assert video.stat().st_size > 1000  # encoded in the actor, written by the driver


def test_diffusion_policy_on_ray_matches_local(tmp_path) -> None:
    from so101_sim.harness.policies.lerobot import LeRobotPolicy

    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "ckpt", input_size=SMALL,
                                          dataset_image_size=(96, 128))
    task = str(short_task(tmp_path, max_steps=40))
    policy = LeRobotPolicy(ckpt, log=lambda _: None)
    runs = {backend: evaluate(policy, task=task, episodes=4, n_envs=n, videos=0,
                              backend=backend, out_dir=tmp_path / backend, **_quiet())
            for backend, n in (("local", 1), ("ray", 3))}
    assert _outcomes(runs["local"]) == _outcomes(runs["ray"])
    assert len({e["actions_sha"] for e in runs["ray"]["per_episode"]}) == 4


def test_save_rollouts_on_ray(expert_local, tmp_path) -> None:
    """The taped episodes come back from the actors as bytes: same dataset as local."""
    res = evaluate("expert", episodes=2, n_envs=2, videos=0, backend="ray", image_size=SMALL,
                   out_dir=tmp_path / "run", save_rollouts=tmp_path / "ds", **_quiet())
    assert _outcomes(res) == _outcomes(expert_local)[:2]
    assert stored_seeds(tmp_path / "ds") == [100000, 100001]
    cols = columns_by_seed(tmp_path / "ds", ("action",))
    for e in res["per_episode"]:
        digest = hashlib.sha256(cols[e["seed"]]["action"].astype(np.float32).tobytes())
        assert digest.hexdigest()[:16] == e["actions_sha"]


def _our_actor_pids() -> list[int]:
    """Pids of WorkerActor processes started by this test process's Ray runtime."""
    me, out = os.getpid(), []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().split(b"\0")[0].decode()
            pid = int(d.name)
            if not cmd.startswith("ray::WorkerActor"):
                continue
            p = pid
            while p > 1:  # descends from us: the runtime ray.init started here
                p = int((Path("/proc") / str(p) / "stat").read_text().rsplit(")", 1)[1].split()[1])
                if p == me:
                    out.append(pid)
                    break
        except (OSError, ValueError, IndexError):
            continue
    return out


def test_killed_actor_is_replaced_and_its_episode_rerun(expert_local, tmp_path) -> None:
    out = tmp_path / "run"
    killed: list[int] = []
    # actors of the previous test's pool may still be exiting (ray.kill does not wait): on a
    # busy machine killing one of those would kill nothing of this run
    stale = set(_our_actor_pids())

    def killer() -> None:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not killed:
            f = out / "episodes.jsonl"
            if f.exists() and f.read_text().count("\n") >= 1:
                pids = [p for p in _our_actor_pids() if p not in stale]
                if pids:
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(pids[0])
            time.sleep(0.05)

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    res = evaluate("expert", episodes=SEEDS, n_envs=2, videos=0, backend="ray", out_dir=out,
                   **{**_quiet(), "report": True})
    thread.join()
    assert killed, "no actor was killed"
    assert _outcomes(res) == _outcomes(expert_local)
    errors = [json.loads(x) for x in (out / "episodes.jsonl").read_text().splitlines()
              if json.loads(x)["status"] == "error"]
    assert errors and "died" in errors[0]["error"]
    assert res["config"]["workers"]["restarts"] >= 1 and res["config"]["reruns"]
    report = (out / "report.md").read_text()
    assert "re-run" in report and "replaced after dying" in report


def test_resume_on_ray(expert_local, tmp_path) -> None:
    out = tmp_path / "run"
    evaluate("expert", episodes=4, n_envs=2, videos=0, backend="ray", out_dir=out, **_quiet())
    lines = (out / "episodes.jsonl").read_text().splitlines()
    (out / "episodes.jsonl").write_text("\n".join(lines[:2]) + "\n" + lines[2][:30])  # torn
    logs: list[str] = []
    res = evaluate("expert", episodes=4, n_envs=3, videos=0, backend="ray", out_dir=out,
                   resume=True, **{**_quiet(), "log": logs.append})
    assert "(2 done, 2 to run)" in logs[0]
    assert _outcomes(res) == _outcomes(expert_local)[:4]
    for line in (out / "episodes.jsonl").read_text().splitlines():
        json.loads(line)  # the torn line was dropped, not glued to the next record


def _columns(root: Path) -> dict[int, dict[str, np.ndarray]]:
    return columns_by_seed(root, ("action", "observation.state", "initial_cube_pose"))


def _frames(root: Path) -> np.ndarray:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/so101_pick_place", root=root)
    picks = [0, len(ds) // 2, len(ds) - 1]
    return np.stack([np.stack([ds[i][f"observation.images.{c}"].numpy()
                               for c in ("front", "side")]) for i in picks])


def test_record_on_ray_matches_local(tmp_path) -> None:
    local = record(tmp_path / "local", 2, image_size=SMALL, progress=False, workers=1)
    on_ray = record(tmp_path / "ray", 2, image_size=SMALL, progress=False, workers=2,
                    backend="ray")
    assert on_ray["backend"] == "ray" and on_ray["episodes"] == local["episodes"] == 2
    assert stored_seeds(tmp_path / "ray") == stored_seeds(tmp_path / "local") == [0, 1]
    a, b = _columns(tmp_path / "local"), _columns(tmp_path / "ray")
    for seed in a:
        for col in a[seed]:
            assert np.array_equal(a[seed][col], b[seed][col]), (seed, col)
    assert np.array_equal(_frames(tmp_path / "local"), _frames(tmp_path / "ray"))
    for name in (".so101_spool", ".so101_tmp"):
        assert not (tmp_path / "ray" / name).exists()
