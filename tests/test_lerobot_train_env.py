"""lerobot-train with `--env.type=so101_pick_place`: the envs that evaluate the policy during
training send the task, cameras and frame size of the dataset it trains on.

Before, they sent pick_place's front and side cameras at 480x640 whatever the dataset held: a
diffusion policy fitted to 96x128 demos stopped at its first evaluation step with "mat1 and
mat2 shapes cannot be multiplied" (after the training before it), one fitted to wrist-camera
demos with a KeyError, and one fitted to stack demos was evaluated on pick_place."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import av
import pytest
from lerobot.envs.factory import make_env, make_env_config
from lerobot.envs.utils import close_envs

from so101_sim.dataset_reads import DatasetReads, fine_tune_problem
from so101_sim.harness.trained_on import default_task
from so101_sim.lerobot_plugin import ENV_TYPE
from so101_sim.record.api import record
from so101_sim.tasks import load_task
from so101_sim.train.checkpoint import SEEDS_KEY, TASK_KEY, TEXTS_KEY, demos_of
from so101_sim.utils.lerobot_cli import TAG

H, W = 96, 128  # the smallest size the default 84x84 crop of a diffusion policy fits
CAMERAS = ["front", "side", "wrist"]
SHIPPED = Path(__file__).resolve().parents[1] / "policy" / "pick_place_diffusion"


@pytest.fixture(scope="module")
def stack_wrist(tmp_path_factory) -> Path:
    """One stack demo with the wrist camera at 96x128, as `so101-sim record` writes it."""
    out = tmp_path_factory.mktemp("lt") / "stack_wrist"
    record(out, 1, task="stack", image_size=(H, W), cameras=CAMERAS, progress=False)
    return out


def _envs(monkeypatch, argv: list[str], **fields):
    monkeypatch.setattr(sys, "argv", ["lerobot-train", *argv])
    return make_env_config(ENV_TYPE, **fields)


def test_the_env_takes_what_the_line_leaves_unset_from_the_dataset(stack_wrist, monkeypatch,
                                                                   caplog) -> None:
    line = [f"--dataset.repo_id=local/{stack_wrist.name}", f"--dataset.root={stack_wrist}",
            "--policy.type=diffusion"]
    with caplog.at_level("INFO"):
        cfg = _envs(monkeypatch, line)
    assert (cfg.task, cfg.cameras, cfg.image_height, cfg.image_width) == ("stack", CAMERAS, H, W)
    assert sorted(k for k in cfg.features if k.startswith("pixels/")) == [
        f"pixels/{cam}" for cam in CAMERAS]
    assert [r.getMessage() for r in caplog.records] == [
        f"--env.type={ENV_TYPE}: task stack, cameras front, side, wrist, 96x128 frames, as in "
        f"dataset {stack_wrist}, so that the policy trained on it is evaluated on what it "
        "learns from (--env.task, --env.cameras, --env.image_height and --env.image_width "
        "choose others)"]
    envs = make_env(cfg, n_envs=1, use_async_envs=False)
    try:
        env = envs[ENV_TYPE][0]
        obs, _ = env.reset(seed=[100000])
        assert {cam: obs["pixels"][cam].shape for cam in CAMERAS} == {
            cam: (1, H, W, 3) for cam in CAMERAS}
        assert env.envs[0].unwrapped.task.name == "stack"
    finally:
        close_envs(envs)

    # what the line sets is kept; what differs from the dataset gets one warning each
    caplog.clear()
    with caplog.at_level("INFO"):
        cfg = _envs(monkeypatch, [*line, "--env.task=pick_place", "--env.image_height=480"],
                    task="pick_place", image_height=480)
    assert (cfg.task, cfg.cameras, cfg.image_height, cfg.image_width) == (
        "pick_place", CAMERAS, 480, 640)
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"--env.type={ENV_TYPE}: dataset {stack_wrist} holds frames of front 96x128, side "
        "96x128, wrist 96x128, and this env sends 480x640: lerobot resizes nothing on the way, "
        "so the policy trained on it would be evaluated on frames unlike its demos; drop "
        "--env.image_height and --env.image_width, or set them to 96 and 128",
        f"--env.type={ENV_TYPE}: dataset {stack_wrist} holds demos of task stack, and "
        "--env.task=pick_place evaluates the policy trained on them on pick_place; drop "
        "--env.task, or pass --env.task=stack"]

    # a resumed run (--config_path) keeps its saved env config: nothing is taken
    cfg = _envs(monkeypatch, [*line, "--config_path=x/train_config.json"])
    assert (cfg.task, cfg.cameras, cfg.image_height) == ("pick_place", None, 480)


def test_a_camera_the_dataset_holds_and_the_env_would_not_send_is_refused(
        stack_wrist, monkeypatch, caplog) -> None:
    """A diffusion or ACT policy reads every camera it was trained on: its first evaluation
    step would stop, so the command stops before training; other types get a warning."""
    line = [f"--dataset.root={stack_wrist}", "--dataset.repo_id=local/x"]
    with pytest.raises(ValueError) as caught:
        _envs(monkeypatch, [*line, "--policy.type=diffusion", "--env.cameras=[front,side]"],
              cameras=["front", "side"])
    assert getattr(caught.value, TAG) == f"--env.type={ENV_TYPE}"
    assert str(caught.value) == (
        f"dataset {stack_wrist} holds camera wrist, and this env sends front, side: a "
        "diffusion policy's first evaluation step would stop with KeyError "
        "'observation.images.wrist'; drop --env.cameras (the env then sends the dataset's "
        "cameras)")
    with pytest.raises(ValueError, match=r"sends no camera frames: .*; drop --env\.obs_type=state"):
        _envs(monkeypatch, [*line, "--policy.type=act"], obs_type="state")
    with caplog.at_level("INFO"):
        _envs(monkeypatch, [*line, "--policy.type=smolvla"], cameras=["front"])
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"--env.type={ENV_TYPE}: dataset {stack_wrist} holds cameras side, wrist, and this env "
        "sends front: the policy trained on it would be evaluated without them; drop "
        "--env.cameras (the env then sends the dataset's cameras)"]
    with pytest.raises(ValueError, match=r"cameras=\['front', 'top'\] is invalid; expected "
                       r"distinct names from front, side, wrist, e\.g\. "
                       r"--env\.cameras='\[front,side,wrist\]'"):
        _envs(monkeypatch, line, cameras=["front", "top"])


def test_a_task_file_that_is_not_here_is_named(stack_wrist, tmp_path, monkeypatch,
                                               caplog) -> None:
    """Demos recorded from a task file on another machine: the env keeps its default task and
    says which task the demos were (what the env reads of a dataset: info.json, the sidecar)."""
    moved = tmp_path / "moved"
    (moved / "meta").mkdir(parents=True)
    shutil.copy(stack_wrist / "meta" / "info.json", moved / "meta")
    (moved / "so101_sim_recording.json").write_text(json.dumps({"task": "/elsewhere/s2.toml"}))
    with caplog.at_level("INFO"):
        cfg = _envs(monkeypatch, [f"--dataset.root={moved}", "--policy.type=diffusion"])
    assert (cfg.task, cfg.cameras) == ("pick_place", CAMERAS)
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"--env.type={ENV_TYPE}: dataset {moved} holds demos of task /elsewhere/s2.toml, which "
        "does not load here, so the policy trained on them would be evaluated on pick_place; "
        "pass --env.task with that task's file"]


def test_fine_tuning_a_policy_on_frames_of_another_size_is_named(stack_wrist, monkeypatch,
                                                                 caplog) -> None:
    """lerobot-train --policy.path=<the shipped 60x80 policy> on 96x128 demos trained on crops
    of the wrong frames without a word (checked: rc 0, no warning); now one warning names
    so101-sim train --init-from, which resizes as the policy's training did."""
    line = [f"--dataset.root={stack_wrist}", "--dataset.repo_id=local/x",
            f"--policy.path={SHIPPED}"]
    with caplog.at_level("INFO"):
        cfg = _envs(monkeypatch, line)
    assert (cfg.image_height, cfg.image_width) == (60, 80)  # the policy decides what is sent
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"--env.type={ENV_TYPE}: {SHIPPED} takes camera frames of 60x80, and dataset "
        f"{stack_wrist} holds 96x128 (front): lerobot-train hands a policy the dataset's frames "
        "as they are, so it would learn from other pictures than it sees; fine-tune it with "
        f"`so101-sim train --dataset {stack_wrist} --init-from {SHIPPED} --out RUN` (which "
        "resizes as its training did), or record the dataset at 60x80"]
    assert fine_tune_problem([*line, "--config_path=x.json"], None) is None
    assert fine_tune_problem([f"--policy.path={SHIPPED}"], None) is None


def test_the_dataset_is_found_where_lerobot_looks_for_it(stack_wrist, tmp_path) -> None:
    """--dataset.root, else lerobot's home / --dataset.repo_id; a policy folder on the line
    decides instead, and a folder that is no dataset is left to lerobot to report."""
    home = stack_wrist.parent
    found = DatasetReads.of([f"--dataset.repo_id={stack_wrist.name}"], home)
    assert found is not None and found.root == stack_wrist and found.task == "stack"
    assert found.sizes == {cam: (H, W) for cam in CAMERAS}
    assert DatasetReads.of([f"--dataset.root={tmp_path}"], home) is None
    assert DatasetReads.of([f"--dataset.root={stack_wrist}", f"--policy.path={SHIPPED}"],
                           home) is None


def test_lerobot_train_evaluates_on_what_the_dataset_holds(stack_wrist, tmp_path, monkeypatch,
                                                           caplog) -> None:
    """The real `lerobot-train`, no --env.* flag but the type: one step, then an evaluation
    episode in the envs it built. Before, that evaluation stopped with a KeyError. Its
    checkpoint is then evaluated on stack by so101-sim eval and lerobot-eval."""
    out = tmp_path / "run"
    cmd = [str(Path(sys.executable).parent / "lerobot-train"),
           f"--dataset.repo_id=local/{stack_wrist.name}", f"--dataset.root={stack_wrist}",
           "--policy.type=diffusion", "--policy.device=cpu", "--policy.push_to_hub=false",
           "--policy.pretrained_backbone_weights=null", "--policy.down_dims=[32,64]",
           "--policy.horizon=8", "--policy.n_action_steps=2", "--policy.num_inference_steps=1",
           f"--env.type={ENV_TYPE}", "--env.episode_length=3", "--env_eval_freq=1",
           "--eval.n_episodes=1", "--eval.batch_size=1", "--steps=1", "--batch_size=2",
           "--num_workers=0", "--wandb.enable=false", "--save_freq=1",
           f"--output_dir={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env={**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    said = proc.stdout + proc.stderr
    assert f"--env.type={ENV_TYPE}: task stack, cameras front, side, wrist, 96x128 frames" in said
    assert "'n_episodes': 1" in said
    videos = list((out / "eval").rglob("*.mp4"))
    assert len(videos) == 1
    with av.open(str(videos[0])) as video:  # the three cameras side by side, as recorded
        stream = video.streams.video[0]
        assert (stream.height, stream.width) == (H, 3 * W)

    # so101-sim eval of that checkpoint runs on the demos' task: from the dataset its
    # train_config.json names, else from its env (a policy fitted to stack demos scored 0 on
    # the default pick_place, without a word)
    policy = out / "checkpoints" / "last" / "pretrained_model"
    assert demos_of(policy) == {TASK_KEY: "stack", TEXTS_KEY: [load_task("stack").description],
                                SEEDS_KEY: []}
    assert default_task(str(policy), "pick_place") == "stack"
    # and so does lerobot-eval with it and no --env.* flag but the type
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={policy}"])
    cfg = make_env_config(ENV_TYPE)
    assert (cfg.task, cfg.cameras, cfg.image_height, cfg.image_width) == ("stack", CAMERAS, H, W)
    with caplog.at_level("INFO"):
        close_envs(make_env(cfg, n_envs=1, use_async_envs=False))
    assert [r.getMessage() for r in caplog.records] == [
        f"--env.type={ENV_TYPE}: task stack, cameras front, side, wrist, 96x128 frames, as "
        f"{policy} was trained on (lerobot-eval hands the policy the frames as they are; "
        "--env.task, --env.cameras, --env.image_height and --env.image_width choose others)"]
    config = json.loads((policy / "train_config.json").read_text())
    config["dataset"]["root"] = str(tmp_path / "moved")
    (policy / "train_config.json").write_text(json.dumps(config))
    assert demos_of(policy) == {TASK_KEY: "stack"}
    config["env"] = None
    (policy / "train_config.json").write_text(json.dumps(config))
    assert demos_of(policy) == {} and default_task(str(policy), "pick_place") == "pick_place"
