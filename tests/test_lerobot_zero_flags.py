"""lerobot finds the env by itself: the lerobot_env_so101_sim distribution, `lerobot-eval` run as
users run it, and the Hub env file through lerobot's own loader."""

from __future__ import annotations

import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from tiny_policy import make_tiny_diffusion_checkpoint, short_task

from so101_sim.harness.compare import load_run
from so101_sim.lerobot_plugin import ENV_TYPE, SO101PickPlaceEnvConfig

BIN = Path(sys.executable).parent
H, W = 48, 64
MODULE = "lerobot.scripts.lerobot_eval"


def test_plugin_distribution_is_named_for_lerobot_discovery():
    dist = importlib.metadata.distribution("lerobot_env_so101_sim")
    assert dist.metadata["Name"] == "lerobot_env_so101_sim"  # underscores: lerobot's prefix
    code = ("import sys; from lerobot.utils.import_utils import register_third_party_plugins; "
            "from lerobot.envs.configs import EnvConfig; "
            "assert 'so101_sim.lerobot_plugin' not in sys.modules; "
            "register_third_party_plugins(); print(sorted(EnvConfig.get_known_choices()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True).stdout
    assert f"'{ENV_TYPE}'" in out


def test_fps_and_episode_length_follow_the_task(tmp_path):
    cfg = SO101PickPlaceEnvConfig(task=str(short_task(tmp_path, max_steps=48)))
    assert (cfg.fps, cfg.episode_length) == (30, 48)
    assert SO101PickPlaceEnvConfig().episode_length == 300
    with pytest.raises(ValueError, match="max_steps=48"):
        SO101PickPlaceEnvConfig(task=str(tmp_path / "pick_place_48.toml"), episode_length=49)


@pytest.mark.usefixtures("child_tmpdir")
def test_lerobot_eval_runs_without_discovery_flags(tmp_path):
    """`lerobot-eval --env.type=so101_pick_place --env.task=... --policy.path=...`, nothing else
    about the plugin or the frame size: the entry point users run, in its own process. The env
    sends the policy's input size (lerobot resizes nothing; 480x640 frames gave a 60x80 policy
    0% before) and says so in one line."""
    ckpt = make_tiny_diffusion_checkpoint(tmp_path / "ckpt", input_size=(H, W),
                                          dataset_image_size=None)
    task = short_task(tmp_path, max_steps=32)
    out = tmp_path / "out"
    cmd = [str(BIN / "lerobot-eval"), f"--env.type={ENV_TYPE}", f"--env.task={task}",
           f"--policy.path={ckpt}",
           "--policy.device=cpu", "--eval.n_episodes=2", "--eval.batch_size=2",
           f"--output_dir={out}", "--seed=100000"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                         env={**env, "PYTHONPROFILEIMPORTTIME": "1"})
    assert run.returncode == 0, run.stderr[-3000:]
    assert "Imported third-party plugin: lerobot_env_so101_sim" in run.stderr
    # lerobot-eval's module (torch, lerobot) is imported by the command and by the fork server
    # of its 2 env workers, which find it there (each imported it itself before)
    imported = [ln for ln in run.stderr.splitlines()
                if ln.startswith("import time:") and ln.split("|")[-1].strip() == MODULE]
    assert len(imported) == 2, imported
    assert (f"--env.type={ENV_TYPE}: {H}x{W} frames, as {ckpt} was trained on (lerobot-eval "
            "hands the policy the frames as they are; --env.task, --env.cameras, "
            "--env.image_height and --env.image_width choose others)") in run.stderr
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 2
    assert "Traceback" not in run.stderr and "libtorchcodec" not in run.stderr
    # its result keeps no seed per episode: `so101-sim compare` says so, not "edited"
    with pytest.raises(ValueError, match=r"is lerobot-eval's result \(.*% on 2 episodes\), "
                                         "which keeps no seed per episode"):
        load_run(out)

    bad = subprocess.run([*cmd[:2], "--env.task=no_such_task", *cmd[3:]], capture_output=True,
                         text=True, timeout=600, env=env)
    assert bad.returncode != 0 and "Traceback" not in bad.stderr, bad.stderr[-3000:]
    assert bad.stderr.strip().splitlines()[-1].startswith(
        f"lerobot-eval: error: --env.type={ENV_TYPE}: unknown task 'no_such_task'; expected")

    # a training run's folder for --policy.path: lerobot's traceback ("config.json not found
    # in ...") became one line naming the policy inside it
    run_dir = tmp_path / "run"
    shutil.copytree(ckpt, run_dir / "pretrained_model")
    bad = subprocess.run([*(w for w in cmd if not w.startswith("--policy.path=")),
                          f"--policy.path={run_dir}"], capture_output=True, text=True,
                         timeout=600, env=env)
    assert bad.returncode != 0 and "Traceback" not in bad.stderr, bad.stderr[-3000:]
    assert bad.stderr.strip().splitlines()[-1] == (
        f"lerobot-eval: error: --policy.path={run_dir} holds no config.json, so lerobot cannot "
        f"load a policy from it; did you mean --policy.path={run_dir / 'pretrained_model'}? "
        "(so101-sim train keeps its final policy in RUN/pretrained_model, lerobot-train in "
        "checkpoints/last/pretrained_model)")


def _local_hub_repo(cache: Path, repo_id: str, files: dict[str, Path]) -> None:
    """A Hub repo as huggingface_hub caches it (what `hf download` leaves), so lerobot's loader
    resolves it offline. lerobot 0.6.1 passes the string to `hf_hub_download`, which rejects
    filesystem paths, so a local repo is served from the cache."""
    commit = "0" * 40
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(commit)
    snap = repo / "snapshots" / commit
    snap.mkdir(parents=True)
    for name, src in files.items():
        shutil.copy(src, snap / name)


def test_hub_env_file_loads_through_lerobots_loader(tmp_path, monkeypatch):
    import numpy as np
    from lerobot.envs.factory import make_env
    from lerobot.envs.utils import close_envs

    import so101_sim.hub_env

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("SO101_IMAGE_SIZE", f"{H}x{W}")
    monkeypatch.setenv("SO101_TASK", str(short_task(tmp_path, max_steps=32)))
    _local_hub_repo(tmp_path / "hub", "someone/so101-sim", {"env.py": so101_sim.hub_env.__file__})
    with pytest.raises(RuntimeError, match="Refusing to execute remote code"):
        make_env("someone/so101-sim", hub_cache_dir=str(tmp_path / "hub"))
    envs = make_env("someone/so101-sim", n_envs=2, trust_remote_code=True,
                    hub_cache_dir=str(tmp_path / "hub"))
    try:
        vec = envs[ENV_TYPE][0]
        assert vec.num_envs == 2
        obs, _ = vec.reset(seed=[100_000, 100_001])
        assert obs["pixels"]["front"].shape == (2, H, W, 3)
        assert vec.call("_max_episode_steps")[0] == 32
        obs, *_ = vec.step(np.stack([obs["agent_pos"][0]] * 2))
        assert obs["agent_pos"].shape == (2, 6)
    finally:
        close_envs(envs)
