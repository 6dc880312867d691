"""The LeRobot env plugin, exercised through lerobot 0.6.1's own factory and preprocessing."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import gymnasium as gym
import numpy as np
import pytest
import torch
from lerobot.configs import FeatureType
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env, make_env_config
from lerobot.envs.utils import (
    NEW_ROLLOUT_OPTION,
    close_envs,
    env_to_policy_features,
    preprocess_observation,
)

from so101_sim.lerobot_plugin import ENV_TYPE, SO101PickPlaceEnvConfig
from so101_sim.tasks import load_task

H, W = 96, 128
EPISODE_LENGTH = 4


@pytest.fixture(scope="module", params=["pixels_agent_pos", "pixels_agent_pos_env_state"])
def built(request: pytest.FixtureRequest):
    """(config, vector env) built by lerobot's make_env, shared by the tests of a module."""
    cfg = make_env_config(ENV_TYPE, obs_type=request.param, image_height=H, image_width=W,
                          episode_length=EPISODE_LENGTH)
    envs = make_env(cfg, n_envs=1, use_async_envs=False)
    yield cfg, envs
    close_envs(envs)


def _vec(envs: dict) -> gym.vector.VectorEnv:
    assert list(envs) == [ENV_TYPE] and list(envs[ENV_TYPE]) == [0]
    return envs[ENV_TYPE][0]


def test_import_registers_env_type() -> None:
    assert ENV_TYPE in EnvConfig.get_known_choices()
    assert EnvConfig.get_choice_class(ENV_TYPE) is SO101PickPlaceEnvConfig
    cfg = make_env_config(ENV_TYPE)
    assert (cfg.task, cfg.fps, cfg.episode_length, cfg.obs_type) == (
        "pick_place", 30, 300, "pixels_agent_pos")
    assert (cfg.image_height, cfg.image_width, cfg.render_mode) == (480, 640, "rgb_array")
    assert cfg.type == ENV_TYPE and cfg.gym_id == "so101_sim/PickPlace-v0"


@pytest.mark.parametrize(("obs_type", "expected"), [
    ("pixels_agent_pos", {"action", "agent_pos", "pixels/front", "pixels/side"}),
    ("pixels_agent_pos_env_state",
     {"action", "agent_pos", "pixels/front", "pixels/side", "environment_state"}),
    ("state", {"action", "agent_pos", "environment_state"}),
])
def test_features_follow_fields(obs_type: str, expected: set[str]) -> None:
    cfg = SO101PickPlaceEnvConfig(obs_type=obs_type, image_height=H, image_width=W)
    assert set(cfg.features) == expected
    policy_features = env_to_policy_features(cfg)  # fails if features_map lacks a key
    assert policy_features["action"].shape == (6,)
    assert policy_features["observation.state"].shape == (6,)
    if "pixels/front" in expected:
        assert cfg.features["pixels/front"].shape == (H, W, 3)
        assert policy_features["observation.images.side"].shape == (3, H, W)
        assert policy_features["observation.images.side"].type is FeatureType.VISUAL
    if "environment_state" in expected:
        assert policy_features["observation.environment_state"].type is FeatureType.ENV


@pytest.mark.parametrize("kwargs", [
    {"obs_type": "pixels"}, {"fps": 10}, {"episode_length": 301}, {"episode_length": 0},
    {"task": ""}, {"image_height": 0}, {"image_width": 4096}, {"render_mode": "human"},
])
def test_invalid_fields_are_rejected(kwargs: dict) -> None:
    """Each is refused by the config itself, tagged, so a lerobot command prints it in one line
    (not later, from the env's constructor, as a traceback)."""
    from so101_sim.utils.lerobot_cli import TAG

    (name, value), = kwargs.items()
    with pytest.raises(ValueError, match=f"{name}={value!r} is invalid|{name}={value} ") as caught:
        SO101PickPlaceEnvConfig(**kwargs)
    assert getattr(caught.value, TAG) == f"--env.type={ENV_TYPE}"


def test_a_lerobot_command_reports_a_bad_env_value_in_one_line(monkeypatch, capsys) -> None:
    """draccus wraps the config's ValueError in a ParsingError, some 40 lines of traceback; a
    lerobot command prints our message in one line, anything else reports as before."""
    import sys
    from dataclasses import dataclass

    import draccus

    from so101_sim.utils.lerobot_cli import one_line_errors

    reported = []
    monkeypatch.setattr(sys, "excepthook", lambda *a: reported.append(a[1]))
    assert not one_line_errors("/usr/bin/python")  # not a lerobot command: nothing installed
    assert one_line_errors("/venv/bin/lerobot-eval") and one_line_errors("lerobot-eval")

    @dataclass
    class Command:  # a lerobot command's config, as lerobot-eval's has an `env` field
        env: EnvConfig | None = None

    with pytest.raises(draccus.utils.DecodingError) as caught:
        draccus.parse(Command, args=[f"--env.type={ENV_TYPE}", "--env.task=no_such_task"])
    assert "Traceback" not in str(caught.value)
    sys.excepthook(caught.type, caught.value, caught.tb)
    assert capsys.readouterr().err.splitlines() == [
        f"lerobot-eval: error: --env.type={ENV_TYPE}: unknown task 'no_such_task'; expected one "
        "of ['lift', 'pick_place', 'pick_place_anywhere', 'pick_place_dr', 'stack', 'tidy'] or "
        "a path to a task .toml file"]
    other = RuntimeError("not a config error")
    sys.excepthook(RuntimeError, other, None)
    assert reported == [other] and capsys.readouterr().err == ""  # the hook that was there

    # lerobot-train's parser catches draccus's error for its optional `env` and prints only
    # "Couldn't instantiate class SO101PickPlaceEnvConfig"; the line is said all the same
    with pytest.raises(draccus.utils.DecodingError):  # lerobot prints it and exits
        draccus.parse(Command, args=[f"--env.type={ENV_TYPE}", "--env.obs_type=pixels"])
    assert capsys.readouterr().err.splitlines() == [
        f"lerobot-eval: error: --env.type={ENV_TYPE}: obs_type='pixels' is invalid; expected "
        "one of ('pixels_agent_pos', 'pixels_agent_pos_env_state', 'state')"]


def test_make_env_reset_and_preprocess(built) -> None:
    cfg, envs = built
    vec = _vec(envs)
    assert isinstance(vec, gym.vector.SyncVectorEnv) and vec.num_envs == 1
    # lerobot-eval's rollout resets with this option and reads these attributes.
    obs, _ = vec.reset(seed=[0], options={NEW_ROLLOUT_OPTION: True})
    assert vec.call("_max_episode_steps")[0] == EPISODE_LENGTH
    assert isinstance(vec.call("task_description")[0], str)
    assert vec.metadata["render_fps"] == cfg.fps

    batch = preprocess_observation(obs)
    for cam in ("front", "side"):
        img = batch[f"observation.images.{cam}"]
        assert img.dtype == torch.float32 and tuple(img.shape) == (1, 3, H, W)
        assert 0.0 <= img.min() <= img.max() <= 1.0 and img.max() > 0
    assert tuple(batch["observation.state"].shape) == (1, 6)

    # Every declared feature appears, under its mapped name, with the declared shape.
    expected = env_to_policy_features(cfg)
    observed = {k: tuple(v.shape[1:]) for k, v in batch.items()}
    assert set(observed) == set(expected) - {"action"}
    for key, feature in expected.items():
        if key != "action":
            assert observed[key] == feature.shape, key
    assert vec.single_action_space.shape == cfg.features["action"].shape


def test_step_rest_pose_reports_success(built) -> None:
    _, envs = built
    vec = _vec(envs)
    vec.reset(seed=[1])
    rest = np.asarray(load_task("pick_place").rest_pose, dtype=np.float32)[None]
    obs, reward, terminated, truncated, info = vec.step(rest)
    assert "is_success" in info and info["is_success"].shape == (1,)
    assert not info["is_success"][0] and reward.shape == (1,)
    assert obs["agent_pos"].shape == (1, 6)
    np.testing.assert_allclose(obs["agent_pos"][0], rest[0], atol=5.0)  # held near rest
    # The episode cap from the config truncates through gym's TimeLimit.
    for _ in range(EPISODE_LENGTH - 1):
        *_, terminated, truncated, info = vec.step(rest)
    assert truncated[0] and not terminated[0]
    assert "final_info" in info and "is_success" in info["final_info"]


class _RestPosePolicy(torch.nn.Module):
    """Stands in for a trained policy: holds the rest pose and records what it was given."""

    def __init__(self) -> None:
        super().__init__()
        self.rest = torch.tensor(load_task("pick_place").rest_pose, dtype=torch.float32)
        self.seen: list[dict] = []

    def reset(self) -> None:
        self.seen.clear()

    def select_action(self, batch: dict) -> torch.Tensor:
        self.seen.append(batch)
        return self.rest.expand(batch["observation.state"].shape[0], -1).clone()


def test_lerobot_eval_rollout_runs_an_episode(built) -> None:
    """lerobot-eval's own rollout loop (reset options, TimeLimit, task text, is_success)."""
    from lerobot.processor import (
        PolicyProcessorPipeline,
        policy_action_to_transition,
        transition_to_policy_action,
    )
    from lerobot.scripts.lerobot_eval import rollout

    cfg, envs = built
    env_pre, env_post = cfg.get_env_processors()
    post = PolicyProcessorPipeline(steps=[], to_transition=policy_action_to_transition,
                                   to_output=transition_to_policy_action)
    policy = _RestPosePolicy()
    out = rollout(_vec(envs), policy, env_pre, env_post, PolicyProcessorPipeline(steps=[]), post,
                  seeds=[3])
    assert tuple(out["action"].shape) == (1, EPISODE_LENGTH, 6)
    assert out["done"][0, -1] and not out["success"].any()
    first = policy.seen[0]
    assert isinstance(first["task"][0], str) and first["task"][0]
    assert tuple(first["observation.images.front"].shape) == (1, 3, H, W)


def test_lerobot_eval_names_a_policy_that_takes_other_frames(monkeypatch, caplog) -> None:
    """`lerobot-eval --env.type=so101_pick_place --policy.path=policy/pick_place_diffusion`
    with --env.image_height/width other than the policy's 60x80 feeds it frames it was not
    trained on (it centre-crops 54x72 of them): 0% and not a word. Building the envs now says
    so, once. (Without the flags the env sends the policy's size: the test below.)"""
    import sys
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[1] / "policy" / "pick_place_diffusion"
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={shipped}",
                                      f"--env.image_height={H}", f"--env.image_width={W}"])
    found = {}
    for size in ((H, W), (60, 80)):
        caplog.clear()
        cfg = make_env_config(ENV_TYPE, image_height=size[0], image_width=size[1],
                              episode_length=EPISODE_LENGTH)
        with caplog.at_level("WARNING"):
            close_envs(make_env(cfg, n_envs=1, use_async_envs=False))
        found[size] = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert found[(60, 80)] == []  # the policy's own size: nothing to say
    assert found[(H, W)] == [
        f"--env.type={ENV_TYPE}: {shipped} takes camera frames of front 60x80, side 60x80, "
        f"and this env sends {H}x{W}: nothing on the way resizes them, so the policy would "
        "see the wrong picture; add --env.image_height=60 --env.image_width=80"]


def test_lerobot_eval_sends_the_frame_size_of_the_policy_on_its_command_line(monkeypatch,
                                                                          caplog) -> None:
    """With no --env.image_height/width, the env sends the frames the command line's policy
    takes (60x80 for the shipped one) and says so once: lerobot
    resizes nothing, and the default 480x640 gave it 0% (with only a warning). A size on the
    command line, or a --config_path that may hold one, is left as chosen."""
    import sys
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[1] / "policy" / "pick_place_diffusion"
    for argv, size in ((["lerobot-eval", f"--policy.path={shipped}"], (60, 80)),
                       (["lerobot-eval", "--policy.path", str(shipped)], (60, 80)),
                       (["lerobot-eval", f"--policy.path={shipped}", "--env.image_height=480"],
                        (480, 640)),
                       (["lerobot-eval", f"--policy.path={shipped}", "--config_path=c.json"],
                        (480, 640)),
                       (["lerobot-eval", "--policy.path=lerobot/some_hub_id"], (480, 640))):
        monkeypatch.setattr(sys, "argv", argv)
        cfg = make_env_config(ENV_TYPE, episode_length=EPISODE_LENGTH)
        assert (cfg.image_height, cfg.image_width) == size, argv
        assert cfg.features["pixels/front"].shape == (*size, 3)
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={shipped}"])
    cfg = make_env_config(ENV_TYPE, episode_length=EPISODE_LENGTH)
    assert make_env_config(ENV_TYPE, obs_type="state").image_height == 480  # no frames sent
    with caplog.at_level("INFO"):
        envs = make_env(cfg, n_envs=1, use_async_envs=False)
    try:
        obs, _ = _vec(envs).reset(seed=[100000])
        assert obs["pixels"]["front"].shape == (1, 60, 80, 3)
    finally:
        close_envs(envs)
    said = [r.getMessage() for r in caplog.records if "trained on" in r.getMessage()]
    assert said == [f"--env.type={ENV_TYPE}: 60x80 frames, as {shipped} was trained on "
                    "(lerobot-eval hands the policy the frames as they are; --env.task, "
                    "--env.cameras, --env.image_height and --env.image_width choose others)"]
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_lerobot_eval_of_a_policy_on_a_task_its_demos_never_had_says_so(monkeypatch,
                                                                       caplog) -> None:
    """`lerobot-eval --env.task=stack --policy.path=policy/pick_place_diffusion` scored about 0
    without a word; now one warning, as `so101-sim eval --task stack` gives a note. Once:
    lerobot-train builds its envs again at every evaluation from the same config."""
    import sys
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[1] / "policy" / "pick_place_diffusion"
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={shipped}",
                                      "--env.task=stack"])
    cfg = make_env_config(ENV_TYPE, task="stack", episode_length=EPISODE_LENGTH)
    with caplog.at_level("WARNING"):
        for _ in range(2):
            close_envs(make_env(cfg, n_envs=1, use_async_envs=False))
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"--env.type={ENV_TYPE}: stack ('Stack the red cube on top of the blue cube.') is not a "
        f"task {shipped} was trained on (its demos: 'Pick up the red cube and place it on the "
        "green target.'); expect a low rate, or pass the --env.task it learned"]


def _policy_config(folder, kind: str, cameras: list[str], env_state: bool = False):
    """A checkpoint's config.json alone: all the input check reads (as data)."""
    import json

    features = {f"observation.images.{cam}": {"type": "VISUAL", "shape": [3, 60, 80]}
                for cam in cameras}
    if env_state:
        features["observation.environment_state"] = {"type": "ENV", "shape": [10]}
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({"type": kind, "input_features": features}))
    return folder


def test_lerobot_eval_refuses_a_policy_that_reads_a_camera_the_env_does_not_send(
        tmp_path, monkeypatch, caplog) -> None:
    """`lerobot-eval --env.obs_type=state --policy.path=policy/pick_place_diffusion` built its
    envs, loaded the policy and stopped at the first step with KeyError
    'observation.images.front'. Now building the envs says why, in one line, with the fix."""
    import sys
    from pathlib import Path

    from so101_sim.utils.lerobot_cli import TAG

    shipped = Path(__file__).resolve().parents[1] / "policy" / "pick_place_diffusion"
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={shipped}"])
    state = make_env_config(ENV_TYPE, obs_type="state", episode_length=EPISODE_LENGTH)
    with pytest.raises(ValueError) as caught:
        make_env(state, n_envs=1, use_async_envs=False)
    assert getattr(caught.value, TAG) == f"--env.type={ENV_TYPE}"
    assert str(caught.value) == (
        f"{shipped} needs cameras front, side, and this env sends no camera frames: its first "
        "step would stop with KeyError 'observation.images.front'; drop --env.obs_type=state "
        "(the default, pixels_agent_pos, sends front, side)")

    # a rig's camera name: the fix is so101-sim eval's camera map
    rig = _policy_config(tmp_path / "rig", "act", ["top", "front"])
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={rig}"])
    pixels = make_env_config(ENV_TYPE, image_height=60, image_width=80,
                             episode_length=EPISODE_LENGTH)
    with pytest.raises(ValueError, match=r"needs camera top \(it reads top, front\), and this "
                       r"env sends front, side: .*--camera-map top=front$"):
        make_env(pixels, n_envs=1, use_async_envs=False)

    # cameras the sim has: with no --env.cameras, the env sends those the policy reads
    vla = _policy_config(tmp_path / "vla", "smolvla", ["front", "wrist"])
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={vla}"])
    size = {"image_height": 60, "image_width": 80, "episode_length": EPISODE_LENGTH}
    with caplog.at_level("INFO"):
        envs = make_env(make_env_config(ENV_TYPE, **size), n_envs=1, use_async_envs=False)
    try:
        obs, _ = _vec(envs).reset(seed=[100000])
        assert sorted(obs["pixels"]) == ["front", "wrist"]
    finally:
        close_envs(envs)
    assert [r.getMessage() for r in caplog.records if "trained on" in r.getMessage()] == [
        f"--env.type={ENV_TYPE}: cameras front, wrist, as {vla} was trained on (lerobot-eval "
        "hands the policy the frames as they are; --env.task, --env.cameras, "
        "--env.image_height and --env.image_width choose others)"]
    # given cameras without one of them: a policy type that pads a missing camera (smolvla,
    # pi0) runs, with one warning
    caplog.clear()
    with caplog.at_level("WARNING"):
        close_envs(make_env(make_env_config(ENV_TYPE, cameras=["front", "side"], **size),
                            n_envs=1, use_async_envs=False))
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        f"--env.type={ENV_TYPE}: {vla} needs camera wrist (it reads front, wrist), and this env "
        "sends front, side: lerobot would feed it an empty image for each; drop --env.cameras "
        "(the env then sends the cameras the policy reads)"]


def test_lerobot_eval_refuses_a_policy_that_reads_the_env_state_without_its_obs_type(
        tmp_path, monkeypatch, caplog) -> None:
    """A checkpoint trained with observation.environment_state under the default obs_type: a
    KeyError at the first step before; now one line naming the obs_type that sends it."""
    import sys

    policy = _policy_config(tmp_path / "p", "diffusion", ["front", "side"], env_state=True)
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={policy}"])
    size = {"image_height": 60, "image_width": 80, "episode_length": EPISODE_LENGTH}
    with pytest.raises(ValueError) as caught:
        make_env(make_env_config(ENV_TYPE, **size), n_envs=1, use_async_envs=False)
    assert str(caught.value) == (
        f"{policy} needs observation.environment_state (the cube's and target's poses), and "
        "this env sends front, side and the joints: its first step would stop with KeyError "
        "'observation.environment_state'; add --env.obs_type=pixels_agent_pos_env_state")
    with caplog.at_level("WARNING"):
        close_envs(make_env(make_env_config(ENV_TYPE, obs_type="pixels_agent_pos_env_state",
                                            **size), n_envs=1, use_async_envs=False))
    assert [r for r in caplog.records if r.levelname == "WARNING"] == []


def test_python_m_lerobot_modules_count_as_lerobot_commands() -> None:
    """`python -m lerobot.async_inference.robot_client --robot.task=nope` printed draccus's
    traceback: its argv[0] is the module's file, not a lerobot-* script."""
    from so101_sim.utils.lerobot_cli import command_name

    site = "/venv/lib/python3.12/site-packages"
    assert command_name(f"{site}/lerobot/async_inference/robot_client.py") == (
        "lerobot.async_inference.robot_client")
    assert command_name(f"{site}/lerobot/scripts/lerobot_eval.py") == "lerobot.scripts.lerobot_eval"
    assert command_name("/venv/bin/lerobot-record") == "lerobot-record"
    for other in ("/usr/bin/python", f"{site}/so101_sim/cli/__main__.py", "-c", ""):
        assert command_name(other) is None, other
