"""The sim as a LeRobot robot (plugins/lerobot_robot_so101_sim): `--robot.type=so101_sim` and
`--teleop.type=so101_sim_expert` through lerobot's own console scripts, headless and offline,
with small images and short episodes."""

from __future__ import annotations

import importlib.metadata
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from lerobot.robots.config import RobotConfig

sys.path.insert(0, str(Path(__file__).parent))
from eval_folders import write_eval_run
from lerobot_robot_so101_sim import (
    SO101Sim,
    SO101SimConfig,
    SO101SimExpert,
    SO101SimExpertConfig,
    connected_robot,
)
from script_loader import load_script
from tiny_act import make_tiny_act_checkpoint
from tiny_policy import short_task

from so101_sim.tasks import load_task
from so101_sim.utils.units import FEATURE_NAMES

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
AGREEMENT = ROOT / "plugins" / "lerobot_robot_so101_sim" / "agreement.py"
SHIPPED = ROOT / "policy" / "pick_place_diffusion"
H, W = 48, 64
TASK_TEXT = "Pick up the red cube and place it on the green target."


def _env(tmp: Path) -> dict[str, str]:
    return {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
            "HF_LEROBOT_HOME": str(tmp / "lerobot_home"),
            "HF_LEROBOT_CALIBRATION": str(tmp / "calibration")}


def _run(cmd: list[str], tmp: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """A console script as a person runs it, minus the terminal (no keyboard listener), from
    `tmp`: lerobot's async server and client write their logs/ under the cwd."""
    return subprocess.run([str(c) for c in cmd], stdin=subprocess.DEVNULL, capture_output=True,
                          text=True, timeout=timeout, env=_env(tmp), cwd=tmp, check=False)


def _outcomes(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _robot(tmp: Path, **kw) -> SO101Sim:
    cfg = dict(image_height=H, image_width=W, realtime=False, calibration_dir=tmp / "cal")
    return SO101Sim(SO101SimConfig(**{**cfg, **kw}))


# ------------------------------------------------------------------ discovery, features, rules
def test_one_distribution_registers_robot_and_teleop():
    dist = importlib.metadata.distribution("lerobot_robot_so101_sim")
    assert dist.metadata["Name"] == "lerobot_robot_so101_sim"  # underscores: lerobot's prefix
    code = ("import sys; from lerobot.utils.import_utils import register_third_party_plugins; "
            "from lerobot.robots import RobotConfig; "
            "from lerobot.teleoperators import TeleoperatorConfig; "
            "assert 'lerobot_robot_so101_sim' not in sys.modules; "
            "register_third_party_plugins(); "
            "print(sorted(RobotConfig.get_known_choices()), "
            "sorted(TeleoperatorConfig.get_known_choices()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True).stdout
    assert "'so101_sim'" in out and "'so101_sim_expert'" in out


def test_features_are_so101_followers_and_leaders(tmp_path):
    from lerobot.cameras.opencv import OpenCVCameraConfig
    from lerobot.robots.so_follower import SO101Follower, SO101FollowerConfig
    from lerobot.teleoperators.so_leader import SO101Leader, SO101LeaderConfig

    cams = {c: OpenCVCameraConfig(index_or_path=0, width=W, height=H, fps=30)
            for c in ("front", "side")}
    real = SO101Follower(SO101FollowerConfig(port="/dev/null", cameras=cams,
                                             calibration_dir=tmp_path / "real"))
    leader = SO101Leader(SO101LeaderConfig(port="/dev/null", calibration_dir=tmp_path / "lead"))
    sim = _robot(tmp_path)
    expert = SO101SimExpert(SO101SimExpertConfig(calibration_dir=tmp_path / "exp"))
    assert list(sim.observation_features.items()) == list(real.observation_features.items())
    assert list(sim.action_features.items()) == list(real.action_features.items())
    assert list(expert.action_features.items()) == list(leader.action_features.items())
    assert tuple(sim.action_features) == FEATURE_NAMES

    sim.connect()
    try:
        obs = sim.get_observation()
        assert obs["front"].shape == (H, W, 3) and obs["front"].dtype == np.uint8
        joints = np.array([obs[k] for k in FEATURE_NAMES], dtype=np.float32)
        np.testing.assert_array_equal(joints, sim.env.agent_pos())  # LeRobot units, as the env
    finally:
        sim.disconnect()

    # rendered larger and resized with the training resize, like `so101-sim eval`
    from so101_sim.utils.image_pipeline import resize_frames

    big = _robot(tmp_path, render_height=2 * H, render_width=2 * W, mesh_width=W)
    big.connect()
    try:
        frame = big.env.render()
        want = resize_frames(np.stack([frame[:, :2 * W], frame[:, 2 * W:]]), (H, W))
        obs = big.get_observation()
        np.testing.assert_array_equal(obs["side"], want[1].permute(1, 2, 0).numpy())
    finally:
        big.disconnect()


def test_episode_rules_without_and_with_a_dataset(tmp_path):
    """Without a dataset an ended episode starts the next seed at once; while one is recorded
    it holds until lerobot saves (next seed) or discards (same seed), and an episode lerobot
    stops recording first ends as unfinished."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    original_save = LeRobotDataset.__dict__["save_episode"]
    task = short_task(tmp_path, max_steps=12)
    robot = _robot(tmp_path, task=str(task), seed=5, outcomes_path=tmp_path / "out.jsonl")
    expert = SO101SimExpert(SO101SimExpertConfig(calibration_dir=tmp_path / "exp"))
    with pytest.raises(LookupError, match=r"--robot\.type=so101_sim"):
        connected_robot()
    expert.connect()
    robot.connect()
    try:
        assert LeRobotDataset.__dict__["save_episode"] is not original_save  # watched
        assert connected_robot() is robot
        for _ in range(12):
            robot.send_action(expert.get_action())
        assert robot.outcomes[-1]["seed"] == 5 and robot.outcomes[-1]["ended_by"] == "env"
        assert robot.episode[:3] == (1, 6, 0)  # next seed at once: nothing records it

        dataset = SimpleNamespace(num_episodes=0)
        for _ in range(12):  # recorded: frame after each step, as lerobot-record does
            robot.get_observation()
            robot.send_action(expert.get_action())
            robot.on_dataset_event("frame", dataset)
        assert robot.episode == (1, 6, 12, True)  # held
        held = robot.get_observation()
        assert expert.get_action() == robot.held_action()
        robot.send_action({"gripper.pos": 0.0})
        assert robot.episode == (1, 6, 12, True)
        assert robot.get_observation()["front"] is held["front"]
        dataset.num_episodes = 1
        robot.on_dataset_event("saved", dataset)
        assert robot.outcomes[-1]["dataset_episode"] == 0 and robot.episode[:3] == (2, 7, 0)

        for _ in range(3):  # lerobot stops recording after 3 frames (its episode_time_s)
            robot.send_action(expert.get_action())
            robot.on_dataset_event("frame", dataset)
        robot.send_action(expert.get_action())  # a reset-phase step, not recorded
        robot.send_action(expert.get_action())  # -> the episode is over
        cut = robot.outcomes[-1]
        assert (cut["seed"], cut["failure_mode"], cut["ended_by"], cut["steps"]) == \
            (7, "unfinished", "lerobot", 4)
        robot.on_dataset_event("discarded", dataset)  # re-record: the same scene again
        assert robot.episode[:3] == (3, 7, 0) and robot.outcomes[-1]["discarded"]

        # joints left out keep their target; unknown keys and NaN are refused, named
        before = robot.held_action()
        applied = robot.send_action({"gripper.pos": 50.0})
        assert applied["gripper.pos"] == 50.0
        assert applied["elbow_flex.pos"] == pytest.approx(before["elbow_flex.pos"])
        with pytest.raises(ValueError, match=r"\['elbow\.pos'\].*shoulder_pan\.pos"):
            robot.send_action({"elbow.pos": 1.0})
        with pytest.raises(ValueError, match=r"wrist_flex\.pos=nan is not finite"):
            robot.send_action({"wrist_flex.pos": float("nan")})
    finally:
        robot.disconnect()
        expert.disconnect()
    assert LeRobotDataset.__dict__["save_episode"] is original_save  # restored
    written = _outcomes(tmp_path / "out.jsonl")
    assert [r["seed"] for r in written] == [5, 6, 7, 7]
    assert written[-1]["ended_by"] == "disconnect"

    paced = _robot(tmp_path, task=str(task), realtime=True)
    paced.connect()
    try:
        t0 = time.perf_counter()
        for _ in range(7):
            paced.send_action(paced.held_action())
        assert time.perf_counter() - t0 >= 6 / 30  # one step per 1/fps, as the real arm
    finally:
        paced.disconnect()


def test_bad_config_values_are_named(tmp_path):
    from so101_sim.utils.lerobot_cli import TAG

    with pytest.raises(ValueError, match=r"episode_end='later'.*hold") as caught:
        SO101SimConfig(episode_end="later")
    # what a lerobot command prints in one line ahead of the message (utils.lerobot_cli)
    assert getattr(caught.value, TAG) == "--robot.type=so101_sim"
    with pytest.raises(ValueError, match="render_height/width=480x0"):
        SO101SimConfig(render_height=480)
    # the task and the cameras too are checked by the config, so lerobot prints them in one
    # line (SO101Sim(config) runs inside make_robot_from_config, which wraps its errors)
    for bad, match in (({"camera_names": ["top"]}, r"camera_names=\['top'\]"),
                       ({"camera_names": ["front", "front"]}, r"camera_names=\['front', 'front'\]"),
                       ({"task": "lfit"}, r"--robot.task='lfit' is invalid: unknown task 'lfit'"),
                       ({"outcomes_path": tmp_path}, "is invalid: it is a folder"),
                       ({"outcomes_path": Path(__file__) / "o.jsonl"}, "lies under a file")):
        with pytest.raises(ValueError, match=match) as caught:
            SO101SimConfig(calibration_dir=tmp_path, **bad)
        assert getattr(caught.value, TAG) == "--robot.type=so101_sim"


@dataclass
class _Command:  # as lerobot-record's config holds its robot
    robot: RobotConfig


def test_a_real_arms_cameras_flag_gets_the_sims_flags(tmp_path):
    """A real SO-101's command line with `--robot.type=so101_sim` in it kept its
    `--robot.cameras='{laptop: {type: opencv, ...}}'` and got draccus's "The fields `cameras`
    are not valid for SO101SimConfig"; now the line names the flags that choose the sim's."""
    import draccus
    from lerobot.cameras.opencv import OpenCVCameraConfig

    from so101_sim.utils.lerobot_cli import TAG

    real = {"laptop": OpenCVCameraConfig(index_or_path=0, fps=30, width=640, height=480),
            "wrist": OpenCVCameraConfig(index_or_path=1)}  # no fps: the base class's error
    with pytest.raises(ValueError) as caught:
        SO101SimConfig(cameras=real, calibration_dir=tmp_path)
    assert str(caught.value) == (
        "--robot.cameras configures real cameras (laptop, wrist); the sim renders its own: pass "
        "--robot.camera_names='[wrist]' (from front, side, wrist) and --robot.image_height / "
        "--robot.image_width for their size")
    assert getattr(caught.value, TAG) == "--robot.type=so101_sim"

    with pytest.raises(draccus.utils.ParsingError) as parsed:
        draccus.parse(_Command, args=["--robot.type=so101_sim", "--robot.cameras={laptop: "
                                     "{type: opencv, index_or_path: 0, fps: 30}}"])
    assert "configures real cameras (laptop)" in str(parsed.value.__cause__)
    assert SO101SimConfig(calibration_dir=tmp_path).cameras == {}  # unset: nothing to say


def test_a_real_arms_port_is_taken_with_one_line(tmp_path, capsys):
    """`--robot.port` (the real arm requires it) stopped the command at draccus's "fields
    `port` are not valid"; the command runs, saying the port is not used."""
    SO101SimConfig(port="/dev/ttyACM0", calibration_dir=tmp_path)
    assert capsys.readouterr().err.splitlines() == [
        "INFO --robot.type=so101_sim: --robot.port=/dev/ttyACM0 is not used (the sim has no "
        "motor bus)"]
    SO101SimConfig(calibration_dir=tmp_path)
    assert capsys.readouterr().err == ""


def test_a_policy_that_takes_other_frames_is_named_at_connect(tmp_path, monkeypatch, caplog):
    """`lerobot-rollout --policy.path=policy/pick_place_diffusion --robot.type=so101_sim`
    with image flags other than its 60x80 feeds it frames it centre-crops to 54x72: every
    episode failed and nothing said why. (With no size flags the robot takes the policy's
    size: the test below.)"""
    from so101_sim.policy_frames import size_warning

    flags = ("--robot.image_height=60 --robot.image_width=80 --robot.render_height=480 "
             "--robot.render_width=640")
    for argv, fate in ((["lerobot-rollout", f"--policy.path={SHIPPED}"],
                        "nothing on the way resizes them"),
                       (["robot_client", "--pretrained_name_or_path", str(SHIPPED)],
                        "the policy server resizes them by plain bilinear interpolation")):
        warning = size_warning(argv, (480, 640), ["front", "side"])
        assert warning is not None and warning.endswith(f"add {flags}") and fate in warning
        assert "front 60x80, side 60x80" in warning and "sends 480x640" in warning
    assert size_warning([f"--policy.path={SHIPPED}"], (60, 80), ["front", "side"]) is None
    assert size_warning(["--policy.path=lerobot/some_hub_id"], (480, 640), ["front"]) is None
    assert size_warning(["lerobot-teleoperate"], (480, 640), ["front"]) is None

    monkeypatch.setattr(sys, "argv", ["lerobot-rollout", f"--policy.path={SHIPPED}"])
    robot = _robot(tmp_path)  # 48x64 frames
    with caplog.at_level("WARNING"):
        robot.connect()
    robot.disconnect()
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"{robot}: {SHIPPED} takes camera frames of front 60x80, side 60x80, and this robot "
        "sends 48x64: nothing on the way resizes them, so the policy would see the wrong "
        f"picture; add {flags}"]


def test_a_policy_on_the_command_line_sets_the_frames_when_no_size_is_given(tmp_path,
                                                                          monkeypatch, caplog):
    """The same command with no size flags now sends what the policy takes: its 60x80 input,
    rendered at its demos' 480x640 and resized as they were (`so101-sim eval --faithful`'s
    frames), said in the connect line. The shipped policy went from 0 of 2 episodes to 3 of
    3 (README). Sizes on the command line are kept."""
    def config(*flags: str) -> SO101SimConfig:
        monkeypatch.setattr(sys, "argv", ["lerobot-rollout", *flags])
        return SO101SimConfig(realtime=False, calibration_dir=tmp_path / "cal")

    for flags in ([f"--policy.path={SHIPPED}"], ["--pretrained_name_or_path", str(SHIPPED)]):
        cfg = config(*flags)
        assert (cfg.image_size, cfg.render_size, cfg.sized_by) == ((60, 80), (480, 640), SHIPPED)
    for flags in ([f"--policy.path={SHIPPED}", "--robot.image_height=480"],
                  [f"--policy.path={SHIPPED}", "--robot.render_width=640"],
                  [f"--policy.path={SHIPPED}", "--config_path=robot.json"],
                  ["--policy.path=lerobot/some_hub_id"], []):
        cfg = config(*flags)
        assert (cfg.image_size, cfg.render_size, cfg.sized_by) == ((480, 640), (480, 640), None)

    robot = SO101Sim(config(f"--policy.path={SHIPPED}"))
    with caplog.at_level("INFO"):
        robot.connect()
    try:
        assert robot.get_observation()["front"].shape == (60, 80, 3)
    finally:
        robot.disconnect()
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    assert any(r.getMessage().endswith(
        f"cameras front,side at 60x80 (rendered at 480x640, resized with so101_sim's "
        f"resize_frames), the input size of {SHIPPED} (--robot.image_height/width and "
        "render_height/width choose others), not paced (realtime=false)")
        for r in caplog.records)


def test_the_robot_client_asking_for_a_policy_the_server_cannot_run_is_refused(tmp_path,
                                                                             monkeypatch):
    """`python -m lerobot.async_inference.robot_client --policy_type=diffusion
    --pretrained_name_or_path=policy/pick_place_diffusion ...` connected and then waited for
    ever: lerobot 0.6.1's policy server failed every chunk of a diffusion policy (an empty
    "Error in StreamActions: " line in its log, checked by hand). Now it stops at connect."""
    from so101_sim.policy_frames import async_server_problem
    from so101_sim.utils.lerobot_cli import TAG

    client = "lerobot/async_inference/robot_client.py"
    monkeypatch.setattr(sys, "argv", [client, "--policy_type=diffusion",
                                      "--pretrained_name_or_path", str(SHIPPED)])
    robot = _robot(tmp_path)
    with pytest.raises(ValueError) as caught:
        robot.connect()
    assert getattr(caught.value, TAG) == "--robot.type=so101_sim"
    assert str(caught.value).startswith(
        "--policy_type=diffusion: lerobot 0.6.1's policy server calls predict_action_chunk on "
        "one observation, without the observation history a diffusion policy keeps, so every "
        "chunk fails on the server (lerobot issue #3861) and the arm never moves; run it in one "
        f"process instead: lerobot-rollout --strategy.type=base --policy.path={SHIPPED} ")
    assert not robot.is_connected
    for kind in ("tdmpc", "vqbet"):  # the same queues; a hub id as much as a folder
        problem = async_server_problem([client, "--policy_type", kind,
                                        "--pretrained_name_or_path=user/repo"])
        assert problem is not None and problem.fatal and f"a {kind} policy keeps" in problem.text
    for argv in ([client, "--policy_type=act", f"--pretrained_name_or_path={SHIPPED}"],
                 ["lerobot-rollout", "--policy_type=diffusion", f"--policy.path={SHIPPED}"]):
        assert async_server_problem(argv) is None  # ACT serves; lerobot-rollout runs in-process
    # the robot told that its client's server is the patched one: diffusion passes, the
    # types the patch does not fix are still refused, and say so
    diffusion = [client, "--policy_type=diffusion", f"--pretrained_name_or_path={SHIPPED}"]
    assert "--robot.patched_server=true" in async_server_problem(diffusion).text
    assert async_server_problem(diffusion, patched_server=True) is None
    problem = async_server_problem([client, "--policy_type=tdmpc",
                                    "--pretrained_name_or_path=user/repo"], patched_server=True)
    assert problem is not None and problem.fatal and "(patched for diffusion only)" in problem.text


def test_a_run_dataset_or_eval_folder_as_the_policy_is_one_line(tmp_path, monkeypatch):
    """lerobot's CLIs parse --policy.path before anything starts and stopped with a traceback
    ("FileNotFoundError: config.json not found in RUN") for a so101-sim run folder; the
    robot client's --pretrained_name_or_path only fails in the server. Both now get one line
    that names the policy inside, or what the folder is."""
    import shutil

    from so101_sim.policy_frames import folder_problem, missing_config_line
    from so101_sim.utils.lerobot_cli import EXPLAINERS

    assert missing_config_line in EXPLAINERS  # what the excepthook asks, at most once
    assert EXPLAINERS.count(missing_config_line) == 1
    run = tmp_path / "run"
    shutil.copytree(SHIPPED, run / "pretrained_model")
    (tmp_path / "data" / "meta").mkdir(parents=True)
    (tmp_path / "data" / "meta" / "info.json").write_text("{}")
    said = {}
    for name in ("run", "data", "empty"):
        (tmp_path / name).mkdir(exist_ok=True)
        monkeypatch.setattr(sys, "argv", ["lerobot-rollout", f"--policy.path={tmp_path / name}"])
        said[name] = missing_config_line(FileNotFoundError(
            f"config.json not found in {tmp_path / name}"))
    assert said["run"] == (
        f"--policy.path={run} holds no config.json, so lerobot cannot load a policy from it; "
        f"did you mean --policy.path={run / 'pretrained_model'}? (so101-sim train keeps its "
        "final policy in RUN/pretrained_model, lerobot-train in checkpoints/last/pretrained_model)")
    assert said["data"].endswith("from it; it is a LeRobotDataset, which `so101-sim train "
                                 f"--dataset {tmp_path / 'data'} --out RUN` trains a policy on")
    assert said["empty"].endswith("from it; expected a policy checkpoint folder (config.json, "
                                  "model.safetensors)")
    assert missing_config_line(FileNotFoundError("other.json not found")) is None
    monkeypatch.setattr(sys, "argv", ["lerobot-rollout", f"--policy.path={SHIPPED}"])
    assert folder_problem(sys.argv) is None  # a policy folder: nothing to say

    monkeypatch.setattr(sys, "argv", ["lerobot/async_inference/robot_client.py",
                                      "--policy_type=act", f"--pretrained_name_or_path={run}"])
    robot = _robot(tmp_path)
    with pytest.raises(ValueError, match=r"--pretrained_name_or_path=\S+ holds no config.json"):
        robot.connect()
    assert not robot.is_connected


def test_a_policy_that_reads_a_camera_the_robot_does_not_send_is_refused_at_connect(
        tmp_path, monkeypatch):
    """`lerobot-rollout --policy.path=policy/pick_place_diffusion --robot.camera_names='[front]'`
    connected, loaded and stopped at the first step with KeyError 'observation.images.side'."""
    from so101_sim.utils.lerobot_cli import TAG

    monkeypatch.setattr(sys, "argv", ["lerobot-rollout", f"--policy.path={SHIPPED}"])
    robot = _robot(tmp_path, camera_names=["front"])
    with pytest.raises(ValueError) as caught:
        robot.connect()
    assert getattr(caught.value, TAG) == "--robot.type=so101_sim"
    assert str(caught.value) == (
        f"{SHIPPED} needs camera side (it reads front, side), and this robot sends front: its "
        "first step would stop with KeyError 'observation.images.side'; add "
        "--robot.camera_names='[front,side]'")
    assert not robot.is_connected
    with pytest.raises(LookupError):  # refused before it registered for the expert
        connected_robot()
    robot = _robot(tmp_path, camera_names=["front", "side"])
    robot.connect()  # the fix it names
    robot.disconnect()

    # the environment state: the robot sends what the real arm does, so the env is the fix
    config = json.loads((SHIPPED / "config.json").read_text())
    config["input_features"]["observation.environment_state"] = {"type": "ENV", "shape": [10]}
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "config.json").write_text(json.dumps(config))
    monkeypatch.setattr(sys, "argv", ["lerobot-rollout", f"--policy.path={tmp_path / 'p'}"])
    with pytest.raises(ValueError, match=r"needs observation\.environment_state .*, and this "
                       r"robot sends front, side and the joints, as the real arm does: .*"
                       r"evaluate it in the env: `so101-sim eval --policy "):
        _robot(tmp_path).connect()


def test_the_robot_takes_its_task_and_cameras_from_the_policy_on_the_line(
        tmp_path, monkeypatch, caplog):
    """A wrist-camera policy on lerobot-rollout's line was refused at connect ("add
    --robot.camera_names=..."), and one trained on stack demos ran pick_place; now the robot
    sends the cameras it reads on the task of its demos, and says so."""
    config = json.loads((SHIPPED / "config.json").read_text())
    features = config["input_features"]
    features["observation.images.wrist"] = dict(features["observation.images.front"])
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "config.json").write_text(json.dumps(config))
    stack_text = "Stack the red cube on top of the blue cube."
    (tmp_path / "w" / "so101_sim_train.json").write_text(json.dumps(
        {"dataset_task": "stack", "dataset_task_texts": [stack_text]}))
    monkeypatch.setattr(sys, "argv", ["lerobot-rollout", f"--policy.path={tmp_path / 'w'}"])
    robot = _robot(tmp_path)
    assert (robot.config.task, robot.config.camera_names) == ("stack", ["front", "side", "wrist"])
    with caplog.at_level("INFO"):
        robot.connect()
    try:
        obs = robot.get_observation()
        assert {cam: obs[cam].shape for cam in ("front", "side", "wrist")} == {
            cam: (H, W, 3) for cam in ("front", "side", "wrist")}
    finally:
        robot.disconnect()
    assert any(r.getMessage().endswith(
        f"task stack, cameras front,side,wrist at {H}x{W}; task and cameras as {tmp_path / 'w'} "
        "was trained on (--robot.task and --robot.camera_names choose others), not paced "
        "(realtime=false)") for r in caplog.records)
    # given names and task are kept (and the connect check names a missing camera)
    assert _robot(tmp_path, camera_names=["front", "side"]).config.camera_names == [
        "front", "side"]
    monkeypatch.setattr(sys, "argv", [*sys.argv, "--robot.task=lift"])
    caplog.clear()
    with caplog.at_level("INFO"):
        assert _robot(tmp_path, task="lift").config.task == "lift"
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        "--robot.type=so101_sim: lift ('Pick up the red cube and hold it above the table.') is not "
        f"a task {tmp_path / 'w'} was trained on (its demos: '{stack_text}'); expect a low "
        "rate, or pass the --robot.task it learned"]


def test_lerobot_replay_of_a_recording_takes_its_seed_and_task(tmp_path, monkeypatch, caplog):
    """`lerobot-replay --robot.type=so101_sim --dataset.root=DATA --dataset.episode=N` of a
    so101-sim recording replayed the episode's actions on seed 0 of pick_place: they missed the
    cube (checked by hand: "unfinished"). Now the robot takes the episode's seed and the
    recording's task, says so, and the replay solves the task as the recording did."""
    from so101_sim.dataset.reader import read_frames
    from so101_sim.record.api import record

    data = tmp_path / "stack"
    record(data, 1, task="stack", seed_start=5, image_size=(H, W), progress=False)
    monkeypatch.setattr(sys, "argv", ["lerobot-replay", f"--dataset.root={data}",
                                      "--dataset.repo_id=local/stack", "--dataset.episode=0"])
    out = tmp_path / "replayed.jsonl"
    robot = _robot(tmp_path, outcomes_path=out, episode_end="hold")
    assert (robot.config.task, robot.config.seed) == ("stack", 5)
    rows = read_frames(data, ["action"])
    with caplog.at_level("INFO"):
        robot.connect()
    try:
        for action in rows["action"]:
            robot.send_action(dict(zip(FEATURE_NAMES, np.asarray(action, float), strict=True)))
    finally:
        robot.disconnect()
    assert any(r.getMessage().endswith(
        f"task stack, cameras front,side at {H}x{W}; task stack and seed 5 of episode 0 of "
        f"dataset {data} (--robot.task and --robot.seed choose others), not paced "
        "(realtime=false)") for r in caplog.records)
    (replayed,) = _outcomes(out)
    assert (replayed["seed"], replayed["task"], replayed["success"]) == (5, "stack", True)
    # what the line gives is kept
    monkeypatch.setattr(sys, "argv", [*sys.argv, "--robot.seed=7"])
    assert _robot(tmp_path, seed=7).config.seed == 7


def test_the_robots_note_of_dataset_episodes_is_read_as_data(tmp_path, caplog):
    """The seed and task the robot keeps for each saved dataset episode: appended on lerobot's
    save (not for a dataset without a root), read back with torn or ill-typed lines skipped and
    a later line for an episode winning; a folder that cannot take the file is one warning."""
    from lerobot_robot_so101_sim.dataset_events import note_saved_episode

    from so101_sim.dataset import ROBOT_EPISODES, read_robot_episodes

    line = {"dataset_episode": 0, "seed": 4, "task": "stack", "success": True}
    note_saved_episode(SimpleNamespace(num_episodes=1), line)  # no root: nothing to write
    note_saved_episode(SimpleNamespace(root=tmp_path), {**line, "dataset_episode": None})
    assert not (tmp_path / ROBOT_EPISODES).exists()
    note_saved_episode(SimpleNamespace(root=tmp_path), line)
    with open(tmp_path / ROBOT_EPISODES, "a", encoding="utf-8") as f:
        f.write('{"dataset_episode": 1, "seed": "9", "task": "stack"}\n[1, 2]\n')
        f.write('{"dataset_episode": 0, "seed": 6, "task": "stack"}\n{"dataset_episode": 2, "se')
    assert {e: v["seed"] for e, v in read_robot_episodes(tmp_path).items()} == {0: 6}
    assert read_robot_episodes(tmp_path / "none") == {}
    with caplog.at_level("WARNING"):
        note_saved_episode(SimpleNamespace(root=tmp_path / "missing"), line)
    assert [r.getMessage() for r in caplog.records] == [
        f"so101_sim: could not write {ROBOT_EPISODES} in {tmp_path / 'missing'} ([Errno 2] No "
        f"such file or directory: '{tmp_path / 'missing' / ROBOT_EPISODES}'); lerobot-replay of "
        "dataset episode 0 needs --robot.seed=4 --robot.task=stack"]


def test_resumed_recording_starts_after_the_seeds_the_dataset_holds(tmp_path, monkeypatch,
                                                                    caplog):
    """`lerobot-record --resume=true` (or lerobot-rollout's) adds episodes to a dataset, and the
    robot started them at its default seed 0 again: the scenes of the dataset's first
    episodes, twice. Now they start after the seeds the robot noted, and the connect line
    says so."""
    from so101_sim.dataset import append_robot_episode

    data = tmp_path / "demos"
    (data / "meta").mkdir(parents=True)
    (data / "meta" / "info.json").write_text('{"features": {}}')
    for episode, seed in enumerate((3, 4, 9)):
        append_robot_episode(data, {"dataset_episode": episode, "seed": seed,
                                    "task": "pick_place"})
    line = ["lerobot-record", "--robot.type=so101_sim", f"--dataset.root={data}",
            "--dataset.repo_id=local/demos"]
    monkeypatch.setattr(sys, "argv", [*line, "--resume=true"])
    robot = _robot(tmp_path)
    assert robot.config.seed == 10
    with caplog.at_level("INFO"):
        robot.connect()
    try:
        assert robot.episode[:2] == (0, 10)
    finally:
        robot.disconnect()
    assert any(r.getMessage().endswith(
        f"cameras front,side at {H}x{W}; seed 10 on, after the seeds of the 3 episodes dataset "
        f"{data} holds (--robot.seed chooses others), not paced (realtime=false)")
        for r in caplog.records)
    monkeypatch.setattr(sys, "argv", ["lerobot-rollout", *line[1:], "--resume=true"])
    assert _robot(tmp_path).config.seed == 10  # lerobot-rollout into a dataset: the same
    # what the line gives is kept; a new dataset starts at the default seed
    monkeypatch.setattr(sys, "argv", [*line, "--resume=true", "--robot.seed=7"])
    assert _robot(tmp_path, seed=7).config.seed == 7
    monkeypatch.setattr(sys, "argv", line)
    assert _robot(tmp_path).config.seed == 0


def test_recording_without_a_task_text_names_the_one_to_give(tmp_path, monkeypatch, caplog):
    """lerobot-record (or -rollout into a dataset) with no --dataset.single_task stored an
    empty task text on every frame, without a word; now one warning gives the task's own."""
    monkeypatch.setattr(sys, "argv", ["lerobot-record", "--dataset.repo_id=local/x"])
    with caplog.at_level("INFO"):
        _robot(tmp_path, task="stack")
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        "--robot.type=so101_sim: no --dataset.single_task, so every frame's task text is empty; "
        "add --dataset.single_task=\"Stack the red cube on top of the blue cube.\" (task stack)"]
    caplog.clear()
    for argv in (["lerobot-record", "--dataset.repo_id=local/x", "--dataset.single_task=Stack"],
                 ["lerobot-teleoperate"], ["lerobot-rollout", "--strategy.type=base"]):
        monkeypatch.setattr(sys, "argv", argv)
        with caplog.at_level("INFO"):
            _robot(tmp_path)
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_the_expert_finds_its_robot_by_id(tmp_path):
    """Two sim robots in one process: the expert needs --teleop.robot_id, an unknown id names
    the connected ones, and a second robot with a taken id is refused without unregistering
    the first."""
    from lerobot.utils.errors import DeviceAlreadyConnectedError

    a, b = _robot(tmp_path, id="a"), _robot(tmp_path, id="b")
    a.connect()
    b.connect()
    try:
        with pytest.raises(LookupError, match=r"2 so101_sim robots are connected \('a', 'b'\); "
                                              "pass --teleop.robot_id"):
            connected_robot()
        assert connected_robot("b") is b
        with pytest.raises(LookupError, match=r"--robot\.id='c' .*connected: 'a', 'b'"):
            connected_robot("c")
        twin = _robot(tmp_path, id="a")
        with pytest.raises(DeviceAlreadyConnectedError, match=r"--robot\.id='a' is already"):
            twin.connect()
        assert connected_robot("a") is a and not twin.is_connected
        expert = SO101SimExpert(SO101SimExpertConfig(calibration_dir=tmp_path / "e",
                                                     robot_id="a"))
        expert.connect()
        assert set(expert.get_action()) == set(FEATURE_NAMES)
        # from a lerobot command, a wrong --teleop.robot_id is one line (utils.lerobot_cli)
        from so101_sim.utils.lerobot_cli import TAG

        stray = SO101SimExpert(SO101SimExpertConfig(calibration_dir=tmp_path / "s",
                                                    robot_id="c"))
        stray.connect()
        with pytest.raises(LookupError, match=r"--robot\.id='c'") as caught:
            stray.get_action()
        assert getattr(caught.value, TAG) == "--teleop.type=so101_sim_expert"
        a.disconnect()
        assert connected_robot() is b
    finally:
        for robot in (a, b):
            if robot.is_connected:
                robot.disconnect()
    with pytest.raises(LookupError, match="no so101_sim robot is connected"):
        connected_robot()


def _outcome(seed: int, success: bool, failure_mode: str | None = None) -> dict:
    """One line of the robot's outcomes.jsonl, as SO101Sim writes it at an episode's end."""
    return {"seed": seed, "success": success, "steps": 120, "discarded": False,
            "ended_by": "env", "failure_mode": None if success else failure_mode or "dropped"}


def test_agreement_pairs_seeds_with_an_eval_folder(tmp_path, capsys):
    # lerobot's outcomes on seeds 10..14 (14 still running when lerobot's episode ended), the
    # eval's on 9..13: paired on 10..13 as `so101-sim compare` pairs, lerobot as A
    agreement = load_script(AGREEMENT)
    evald = write_eval_run(tmp_path / "eval", {9: True, 10: True, 11: True, 12: False,
                                               13: False}, sha=load_task("pick_place").sha256())
    args = agreement._parser().parse_args(["rollout", "--seed-start", "10", "--episodes", "5",
                                           "--pair", str(evald)])
    pair = agreement._pair_run(evald, load_task("pick_place"), args)
    out = tmp_path / "out"
    out.mkdir()
    rows = [_outcome(10, True), _outcome(11, False), _outcome(12, True), _outcome(13, False),
            _outcome(14, False, "unfinished")]
    (out / "outcomes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert agreement._report(args, out, out / "outcomes.jsonl", [], pair) == 1  # unfinished
    said = capsys.readouterr().out
    paired = json.loads((out / "agreement.json").read_text())["paired"]
    assert paired["n_seeds"] == 4 and paired["seeds"] == "10..13", paired
    assert paired["paired"] == {"both": 1, "only_a": 1, "only_b": 1, "neither": 1}, paired
    assert paired["a"]["policy"].startswith("lerobot-rollout of ") and \
        paired["b"]["run"] == str(evald), paired
    assert paired["mcnemar_p_two_sided"] == 1.0, paired
    assert "paired on 4 seeds of pick_place (10..13): both succeed 1, only A 1, only B 1, " \
        "neither 1" in said, said


def test_agreement_refuses_a_pair_folder_of_another_task_or_seeds_before_it_runs(tmp_path,
                                                                                 capsys):
    agreement = load_script(AGREEMENT)
    stack = write_eval_run(tmp_path / "stack", {100_000: True}, task="stack")
    pick = write_eval_run(tmp_path / "pick", {5: True, 6: False},
                          sha=load_task("pick_place").sha256())
    edited = write_eval_run(tmp_path / "edited", {100_000: True})  # another task_sha256
    for folder, said in [
        (stack, f"--pair {stack} is an eval of task 'stack'; this run is --task 'pick_place'"),
        (edited, f"--pair {edited} is an eval of task 'pick_place' with other settings"),
        (pick, f"--pair {pick} holds seeds 5..6, none of this run's 100000..100001"),
    ]:
        with pytest.raises(SystemExit) as stop:
            agreement.main(["rollout", "--episodes", "2", "--pair", str(folder),
                            "--out", str(tmp_path / "out"), "--policy", str(tmp_path / "no")])
        assert str(stop.value.code).startswith(said), stop.value.code
        assert "pair with the folder of `so101-sim eval --policy" in str(stop.value.code)
    assert not (tmp_path / "out").exists()
    # some of the seeds: said in one line, then the run goes on (here: to the missing policy)
    with pytest.raises(SystemExit, match=r"no config\.json there"):
        agreement.main(["rollout", "--episodes", "3", "--seed-start", "5", "--pair", str(pick),
                        "--out", str(tmp_path / "out"), "--policy", str(tmp_path / "no")])
    assert f"--pair {pick} lacks 1 of the 3 seeds (7)" in capsys.readouterr().out


@pytest.mark.parametrize(("flag", "value", "expected"), [
    ("--episodes", "0", "expected an integer >= 1"),
    ("--seed-start", "-1", "expected an integer >= 0"),
    ("--render-size", "480", "expected HEIGHTxWIDTH, e.g. 480x640"),
    ("--actions-per-chunk", "0", "expected an integer >= 1"),
    # -1 ended in lerobot-rollout's traceback (an episode with no frame), 0 ran the default
    ("--episode-time-s", "-1", "-1 is invalid; expected a finite number > 0"),
    ("--episode-time-s", "0", "0 is invalid; expected a finite number > 0"),
    # 5 ended in lerobot's ValueError once the policy server was up; nan ran a client that
    # never asked for a chunk, until it was killed
    ("--chunk-size-threshold", "5", "5 is invalid; expected a fraction in [0, 1]"),
    ("--chunk-size-threshold", "nan", "nan is invalid; expected a fraction in [0, 1]"),
])
def test_agreement_refuses_a_bad_value_before_it_runs(flag, value, expected, tmp_path, capsys):
    # before, --episodes 0 started lerobot-rollout for no episode and --render-size 480 failed
    # only after the policy folder had been read (a missing one here, so that a value let
    # through fails at once instead of running lerobot-rollout)
    with pytest.raises(SystemExit) as stop:
        load_script(AGREEMENT).main(["rollout", flag, value, "--out", str(tmp_path / "out"),
                                     "--policy", str(tmp_path / "no_policy")])
    said = capsys.readouterr().err
    assert stop.value.code == 2 and flag in said and expected in said, (stop.value.code, said)
    assert not (tmp_path / "out").exists()


def test_agreement_refuses_an_unknown_aggregate_function_before_the_server_starts(tmp_path):
    # before, lerobot's RobotClientConfig raised ValueError once the policy server was up
    with pytest.raises(SystemExit) as stop:
        load_script(AGREEMENT).main(["async", "--patch-diffusion", "--aggregate-fn", "mean",
                                     "--episodes", "1", "--out", str(tmp_path / "out")])
    said = str(stop.value.code)
    assert "--aggregate-fn 'mean' is not one of lerobot's" in said, said
    assert "weighted_average" in said and "latest_only" in said, said
    assert not (tmp_path / "out").exists()


def test_agreement_refuses_a_pair_folder_without_an_eval_before_it_runs(tmp_path):
    # before, --pair was read after the whole lerobot run, which then ended without its summary
    (tmp_path / "not_an_eval").mkdir()
    with pytest.raises(SystemExit) as stop:
        load_script(AGREEMENT).main(["rollout", "--pair", str(tmp_path / "not_an_eval"),
                                     "--out", str(tmp_path / "out"),
                                     "--policy", str(tmp_path / "no_policy")])
    said = str(stop.value.code)
    assert said.startswith(f"--pair: {tmp_path / 'not_an_eval'} has no eval_info.json: "
                           "expected the --out folder of a finished `so101-sim eval`"), said
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("under", ["", "run"], ids=["is-a-file", "under-a-file"])
def test_agreement_refuses_an_out_that_is_a_file(under, tmp_path):
    # before, mkdir ended in a FileExistsError or NotADirectoryError traceback
    (tmp_path / "notes.txt").write_text("mine")
    out = tmp_path / "notes.txt" / under if under else tmp_path / "notes.txt"
    with pytest.raises(SystemExit) as stop:
        load_script(AGREEMENT).main(["rollout", "--out", str(out)])  # the shipped policy
    said = str(stop.value.code)
    assert said.startswith(f"--out {out}: {tmp_path / 'notes.txt'} is a file; expected a "
                           "folder"), said
    assert (tmp_path / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("missing", ["config.json", "model.safetensors"])
def test_agreement_refuses_a_policy_folder_without_its_files_before_it_runs(missing, tmp_path):
    # before, a folder without weights ran: lerobot-rollout or the policy server then failed
    policy = tmp_path / "policy"
    shutil.copytree(SHIPPED, policy)
    (policy / missing).unlink()
    with pytest.raises(SystemExit) as stop:
        load_script(AGREEMENT).main(["rollout", "--policy", str(policy),
                                     "--out", str(tmp_path / "out")])
    said = str(stop.value.code)
    assert said.startswith(f"--policy {policy}: no {missing} there; expected a checkpoint "
                           "folder"), said
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("rename, said", [
    ("laptop", "wants cameras ['laptop']; the env has"),
    (None, "no camera input; this script measures image policies"),
])
def test_agreement_refuses_a_policy_it_cannot_feed_before_it_runs(rename, said, tmp_path):
    # before, these were found once --out was made (and, for async, the server started)
    policy = tmp_path / "policy"
    shutil.copytree(SHIPPED, policy)
    config = json.loads((policy / "config.json").read_text())
    features = config["input_features"]
    for key in [k for k in features if k.startswith("observation.images.")]:
        feature = features.pop(key)
        if rename:
            features[f"observation.images.{rename}"] = feature
    (policy / "config.json").write_text(json.dumps(config))
    with pytest.raises(SystemExit) as stop:
        load_script(AGREEMENT).main(["rollout", "--policy", str(policy),
                                     "--out", str(tmp_path / "out")])
    assert str(stop.value.code).startswith(f"--policy {policy}: ") and said in \
        str(stop.value.code), stop.value.code
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("render_size, want", [
    (None, (480, 640, 0)),  # eval --faithful: the recorded size, with its own mesh detail
    ("120x160", (120, 160, 640)),  # eval --image-size 120x160 keeps the recorded 640 px meshes
    ("60x80", (60, 80, 0)),  # eval --image-size 60x80: the input size, direct, 80 px meshes
])
def test_agreement_renders_as_eval_does_at_the_same_size(render_size, want, tmp_path):
    # before, --render-size 120x160 rendered 160 px meshes where eval keeps the recorded 640 px
    # ones, and the pairing line still said --faithful
    agreement = load_script(AGREEMENT)
    args = agreement._parser().parse_args(
        ["rollout"] + (["--render-size", render_size] if render_size else []))
    flags = agreement._robot_flags(args, agreement._policy_info(SHIPPED), tmp_path / "o.jsonl")
    assert (flags["render_height"], flags["render_width"], flags["mesh_width"]) == want
    assert (flags["image_height"], flags["image_width"]) == (60, 80)


def test_agreement_refuses_an_unknown_task_before_it_runs(tmp_path):
    # before, load_task's error came as a traceback, after --out had been made
    with pytest.raises(SystemExit) as stop:
        load_script(AGREEMENT).main(["rollout", "--task", "pick_plac",
                                     "--out", str(tmp_path / "out")])  # the shipped policy
    said = str(stop.value.code)
    assert said.startswith("--task 'pick_plac' is invalid: unknown task 'pick_plac'"), said
    assert "pick_place" in said and not (tmp_path / "out").exists()


# ------------------------------------------------------------------ lerobot's console scripts
@pytest.mark.slow
@pytest.mark.usefixtures("child_tmpdir")
def test_lerobot_record_with_the_expert_then_train_and_replay(tmp_path):
    """lerobot-record writes one dataset episode per seed, each a success (the expert solves
    seeds 0 and 1); so101-sim's trainer reads it; lerobot-replay re-runs episode 1 exactly.
    lerobot's files keep no seed, so the robot notes each saved episode's seed and task in the
    dataset, and the replay takes them: before, it needed --robot.seed=1 by hand, and without
    it replayed episode 1's actions on seed 0."""
    from lerobot.datasets import LeRobotDataset

    from so101_sim.dataset import read_robot_episodes, recorded_seeds, recorded_task
    from so101_sim.dataset.reader import open_lerobot_dataset
    from so101_sim.dataset_reads import DatasetReads
    from so101_sim.record import replay
    from so101_sim.train.checkpoint import demos_info
    from so101_sim.train.presets import load_preset
    from so101_sim.train.trainer import load_demos

    root, outcomes = tmp_path / "demos", tmp_path / "record.jsonl"
    run = _run([BIN / "lerobot-record", "--robot.type=so101_sim", f"--robot.image_height={H}",
                f"--robot.image_width={W}", f"--robot.outcomes_path={outcomes}",
                "--teleop.type=so101_sim_expert", "--dataset.repo_id=local/so101_sim_demos",
                f"--dataset.root={root}", "--dataset.num_episodes=2",
                "--dataset.episode_time_s=9", "--dataset.reset_time_s=0",
                "--dataset.push_to_hub=false", "--dataset.no_stamp=true",
                f"--dataset.single_task={TASK_TEXT}", "--dataset.rgb_encoder.vcodec=h264",
                "--play_sounds=false"], tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "so101_sim episode 1 (seed 1): success" in run.stderr
    recorded = _outcomes(outcomes)
    assert [(r["seed"], r["success"], r["dataset_episode"]) for r in recorded] == \
        [(0, True, 0), (1, True, 1)]

    noted = read_robot_episodes(root)
    assert [(e, noted[e]["seed"], noted[e]["task"]) for e in sorted(noted)] == \
        [(0, 0, "pick_place"), (1, 1, "pick_place")]
    reads = DatasetReads.at(["lerobot-replay", f"--dataset.root={root}"], None)
    assert (reads.task, reads.episode_seed(1)) == ("pick_place", 1)

    ds = LeRobotDataset("local/so101_sim_demos", root=root)
    assert ds.num_episodes == 2 and ds.meta.robot_type == "so101_sim"
    # what a policy trained on it records of its demos: the task (pick_place's text alone
    # names three tasks of the suite) and no evaluation seed among them
    assert (recorded_task(root), recorded_seeds(root)) == ("pick_place", [0, 1])
    demos = demos_info(recorded_task(root), ds.meta.tasks.index, recorded_seeds(root))
    assert (demos["dataset_task"], demos["dataset_eval_seeds"]) == ("pick_place", [])
    # so101-sim replay re-simulates it: its recorded steps, then the frames held after the end
    assert [replay(root, e) for e in (0, 1)] == [0.0, 0.0]
    assert tuple(ds.meta.features["observation.images.front"]["shape"]) == (H, W, 3)
    assert ds.meta.features["action"]["names"] == list(FEATURE_NAMES)
    demos = load_demos(open_lerobot_dataset(root), load_preset("cpu"), None)
    assert demos.state.shape == (ds.num_frames, 6)
    assert {k: v.shape[1:] for k, v in demos.frames.items()} == \
        {f"observation.images.{c}": (3, 60, 80) for c in ("front", "side")}

    replayed = tmp_path / "replay.jsonl"
    run = _run([BIN / "lerobot-replay", "--robot.type=so101_sim",
                "--robot.episode_end=hold", f"--robot.image_height={H}",
                f"--robot.image_width={W}", f"--robot.outcomes_path={replayed}",
                "--dataset.repo_id=local/so101_sim_demos", f"--dataset.root={root}",
                "--dataset.episode=1", "--play_sounds=false"], tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert f"seed 1 of episode 1 of dataset {root} (--robot.seed chooses others)" in run.stderr
    (again,) = _outcomes(replayed)
    assert (again["seed"], again["success"], again["steps"]) == (1, True, recorded[1]["steps"])


@pytest.mark.slow
@pytest.mark.usefixtures("child_tmpdir")
def test_lerobot_teleoperate_with_the_expert(tmp_path):
    run = _run([BIN / "lerobot-teleoperate", "--robot.type=so101_sim",
                f"--robot.image_height={H}", f"--robot.image_width={W}",
                "--teleop.type=so101_sim_expert", "--teleop_time_s=3"], tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "so101_sim robot connected" in run.stderr
    assert "so101_sim robot disconnected" in run.stderr


@pytest.mark.slow
@pytest.mark.usefixtures("child_tmpdir")
def test_lerobot_rollout_runs_the_shipped_policy(tmp_path):
    """Base strategy for 3 s; the episodic strategy through agreement.py: one dataset episode
    per seed, frames rendered larger and resized to the policy's 60x80 as so101-sim eval does."""
    outcomes = tmp_path / "base.jsonl"
    run = _run([BIN / "lerobot-rollout", "--strategy.type=base", f"--policy.path={SHIPPED}",
                "--robot.type=so101_sim", "--robot.image_height=60", "--robot.image_width=80",
                "--robot.render_height=120", "--robot.render_width=160",
                "--robot.realtime=false", f"--robot.outcomes_path={outcomes}", "--duration=3",
                "--return_to_initial_position=false", "--play_sounds=false"], tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    (base,) = _outcomes(outcomes)
    assert base["ended_by"] == "disconnect" and base["steps"] > 0

    out = tmp_path / "agreement"
    run = _run([sys.executable, AGREEMENT, "rollout", "--episodes", "2", "--seed-start",
                "100000", "--task", short_task(tmp_path, max_steps=20), "--render-size",
                "120x160", "--episode-time-s", "6", "--out", out], tmp_path)
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "seed 100001: " in run.stdout and "success: " in run.stdout
    assert "--seed-start 100000 --image-size 120x160\n" in run.stdout  # how eval renders it
    summary = json.loads((out / "agreement.json").read_text())
    assert summary["episodes"] == 2 and summary["unfinished"] == []
    rows = _outcomes(out / "outcomes.jsonl")
    assert [(r["seed"], r["dataset_episode"], r["steps"]) for r in rows] == \
        [(100000, 0, 20), (100001, 1, 20)]
    from lerobot.datasets import LeRobotDataset

    ds = LeRobotDataset("local/rollout_so101_sim_agreement", root=out / "rollout_dataset")
    assert ds.num_episodes == 2
    assert tuple(ds.meta.features["observation.images.front"]["shape"]) == (60, 80, 3)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["act", "diffusion"])
@pytest.mark.usefixtures("child_tmpdir")
def test_async_inference_drives_the_sim(tmp_path, kind):
    """lerobot's policy server and robot client, unchanged, on a loopback port, for a tiny
    ACT; lerobot 0.6.1's server cannot run a Diffusion Policy with n_obs_steps > 1 (see
    below), so the shipped one is served by lerobot_robot_so101_sim.patched_server, which the
    robot is told with --robot.patched_server=true. --robot.episodes=1 stops the client as
    Ctrl-C would after one episode."""
    if kind == "act":
        ckpt, (h, w) = make_tiny_act_checkpoint(tmp_path / "act", input_size=(H, W)), (H, W)
        server_module, told = "lerobot.async_inference.policy_server", []
    else:
        ckpt, (h, w) = SHIPPED, (60, 80)
        server_module = "lerobot_robot_so101_sim.patched_server"
        told = ["--robot.patched_server=true"]
    port, outcomes = _free_port(), tmp_path / "async.jsonl"
    server = subprocess.Popen([sys.executable, "-m", server_module,
                               "--host=127.0.0.1", f"--port={port}", "--fps=30"],
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=_env(tmp_path), cwd=tmp_path)
    try:
        end = time.monotonic() + 120
        while not _listening(port):
            assert time.monotonic() < end and server.poll() is None, "server did not listen"
            time.sleep(0.2)
        run = _run([sys.executable, "-m", "lerobot.async_inference.robot_client",
                    "--robot.type=so101_sim", f"--robot.task={short_task(tmp_path, 20)}",
                    f"--robot.image_height={h}", f"--robot.image_width={w}", *told,
                    "--robot.episodes=1", f"--robot.outcomes_path={outcomes}",
                    f"--task={TASK_TEXT}", f"--server_address=127.0.0.1:{port}",
                    f"--policy_type={kind}", f"--pretrained_name_or_path={ckpt}",
                    "--policy_device=cpu", "--actions_per_chunk=8"], tmp_path, timeout=240)
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()
    # KeyboardInterrupt is how the client stops (its own finally: robot.disconnect())
    assert run.returncode in (0, 130, -signal.SIGINT), run.stderr[-3000:]
    assert "so101_sim: 1 episode ended (--robot.episodes=1): stopping" in run.stderr
    assert re.search(r"so101_sim robot disconnected: 1 episode ended, [01] succeeded", run.stderr)
    first = _outcomes(outcomes)[0]
    assert (first["seed"], first["ended_by"]) == (0, "env") and 0 < first["steps"] <= 20


@pytest.mark.usefixtures("lerobot_tempfiles")
def test_the_patched_server_runs_a_diffusion_policy_on_one_observation(monkeypatch):
    """lerobot 0.6.1's policy server hands predict_action_chunk one observation and no history:
    the shipped Diffusion Policy (n_obs_steps=2) fails on that unpatched and returns a chunk
    once lerobot_robot_so101_sim.patched_server has patched it."""
    import torch
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot_robot_so101_sim.patched_server import patch_diffusion_single_observation

    # the patch is class-wide: monkeypatch puts lerobot's own method back after the test
    monkeypatch.setattr(DiffusionPolicy, "predict_action_chunk",
                        DiffusionPolicy.predict_action_chunk)
    policy = DiffusionPolicy.from_pretrained(SHIPPED).eval()
    assert policy.config.n_obs_steps == 2
    batch = {key: torch.rand(1, *feature.shape)
             for key, feature in policy.config.input_features.items()}
    with torch.no_grad(), pytest.raises(AssertionError):
        policy.predict_action_chunk(batch)
    patch_diffusion_single_observation()
    patched = DiffusionPolicy.predict_action_chunk
    patch_diffusion_single_observation()  # a second call leaves the first patch alone
    assert DiffusionPolicy.predict_action_chunk is patched
    with torch.no_grad():
        chunk = policy.predict_action_chunk(batch)
    assert tuple(chunk.shape) == (1, policy.config.n_action_steps, len(FEATURE_NAMES))
    assert torch.isfinite(chunk).all()


@pytest.mark.slow
@pytest.mark.usefixtures("child_tmpdir")
def test_agreement_async_names_the_servers_error_on_damaged_weights(tmp_path):
    # before: "could not reach the policy server", though it was up and had raised on them
    policy, out = tmp_path / "policy", tmp_path / "out"
    shutil.copytree(SHIPPED, policy)
    (policy / "model.safetensors").write_bytes(b"not weights")
    run = _run([sys.executable, AGREEMENT, "async", "--patch-diffusion", "--episodes", "1",
                "--policy", policy, "--out", out], tmp_path, timeout=120)
    assert run.returncode == 1, run.stdout + run.stderr[-3000:]
    said = run.stderr[run.stderr.index("the policy server on port"):]
    assert f"did not take --policy {policy}; the end of {out / 'server.log'}:" in said
    assert "SafetensorError" in said  # the server's own error, from its log


@pytest.mark.slow
@pytest.mark.usefixtures("child_tmpdir")
def test_agreement_async_runs_the_shipped_diffusion_policy(tmp_path):
    run = _run([sys.executable, AGREEMENT, "async", "--episodes", "1"], tmp_path)
    assert run.returncode != 0 and "issues/3861" in run.stderr and "--patch-diffusion" in \
        run.stderr  # lerobot 0.6.1's server cannot, unpatched: said before anything starts
    out = tmp_path / "async"
    run = _run([sys.executable, AGREEMENT, "async", "--patch-diffusion", "--episodes", "1",
                "--task", short_task(tmp_path, max_steps=20), "--render-size", "120x160",
                "--out", out, "--policy", os.path.relpath(SHIPPED, tmp_path)], tmp_path)
    # the policy's path as typed, relative to where it was run; the server runs in --out
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "seed 100000: " in run.stdout and "action latency" in run.stdout
    summary = json.loads((out / "agreement.json").read_text())
    assert summary["episodes"] == 1 and summary["latency_ms"]["chunks"] >= 1
    # lerobot's client and server make logs/ in their cwd: here --out, not where it was run
    assert not (tmp_path / "logs").exists()
    assert {p.name.rsplit("_", 1)[0] for p in (out / "logs").glob("*.log")} == {
        "robot_client", "policy_server"}
