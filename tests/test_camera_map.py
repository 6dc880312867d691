"""`so101-sim eval --camera-map`: a checkpoint whose cameras are named after another rig."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from so101_sim.cli import main
from so101_sim.harness.camera_map import (
    describe_camera_map,
    parse_camera_map,
    resolve_camera_map,
)

sys.path.insert(0, str(Path(__file__).parent))
from tiny_policy import make_tiny_diffusion_checkpoint, short_task

MAP = "top=front,wrist=side"


def test_parse_and_resolve_name_the_fix():
    assert parse_camera_map(" top=front, wrist = side ") == {"top": "front", "wrist": "side"}
    for bad, pattern in (("top", "POLICY_CAMERA=ENV_CAMERA"), ("top=front,top=side", "twice"),
                         (",", "empty")):
        with pytest.raises(ValueError, match=pattern):
            parse_camera_map(bad)
    assert resolve_camera_map(["front", "wrist"], {"wrist": "side"}, "ckpt") == {
        "front": "front", "wrist": "side"}
    with pytest.raises(ValueError, match=r"camera 'laptop'.*--camera-map laptop=front"):
        resolve_camera_map(["front", "laptop"], None, "ckpt")
    # the env has a wrist camera too: a rig's `wrist` input takes it unless mapped elsewhere
    assert resolve_camera_map(["front", "wrist"], None, "ckpt") == {
        "front": "front", "wrist": "wrist"}
    with pytest.raises(ValueError, match=r"names \['laptop'\].*cameras are \['top'\]"):
        resolve_camera_map(["top"], {"laptop": "front"}, "ckpt")
    with pytest.raises(ValueError, match=r"maps onto \['phone'\]"):
        resolve_camera_map(["top"], {"top": "phone"}, "ckpt")


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, Path]:
    """The same weights (same seed, same camera order) under two sets of camera names."""
    root = tmp_path_factory.mktemp("ckpts")
    return {names[0]: make_tiny_diffusion_checkpoint(root / names[0], cameras=names,
                                                     dataset_image_size=None)
            for names in (("top", "wrist"), ("front", "side"))}


def _eval(policy: Path, out: Path, task: Path, *extra: str) -> int:
    return main(["eval", "--policy", str(policy), "--task", str(task), "--episodes", "2",
                 "--n-envs", "1", "--videos", "0", "--policy-batch", "1", "--out", str(out),
                 *extra])


def test_mapped_cameras_feed_the_policy_like_native_names(ckpts, tmp_path, capsys):
    task = short_task(tmp_path, max_steps=32)  # >= the success hold_steps
    assert _eval(ckpts["top"], tmp_path / "unmapped", task) == 2
    err = capsys.readouterr().err
    assert "expects camera 'top'" in err and "--camera-map top=front" in err

    assert _eval(ckpts["top"], tmp_path / "mapped", task, "--camera-map", MAP) == 0
    out = capsys.readouterr().out
    said = "cameras: policy top <- env front, policy wrist <- env side"
    assert said in out.strip().splitlines()[-1]  # the summary line
    assert "images: direct: rendered at the policy's input size 48x64" in out
    info = json.loads((tmp_path / "mapped" / "eval_info.json").read_text())
    assert said in info["config"]["images"]
    assert info["config"]["policy_details"]["cameras"] == said.removeprefix("cameras: ")
    assert said in (tmp_path / "mapped" / "report.md").read_text()

    # Same weights under the env's own names: identical rollouts, action for action.
    assert _eval(ckpts["front"], tmp_path / "native", task) == 0
    native = json.loads((tmp_path / "native" / "eval_info.json").read_text())
    digest = [e["actions_sha"] for e in info["per_episode"]]
    assert digest == [e["actions_sha"] for e in native["per_episode"]]
    # Swapped cameras are different inputs: the policy acts differently.
    assert _eval(ckpts["top"], tmp_path / "swapped", task, "--camera-map",
                 "top=side,wrist=front") == 0
    swapped = json.loads((tmp_path / "swapped" / "eval_info.json").read_text())
    assert digest != [e["actions_sha"] for e in swapped["per_episode"]]
    assert swapped["config"]["policy_fingerprint"] != info["config"]["policy_fingerprint"]


def test_bad_camera_map_is_a_usage_error(capsys):
    with pytest.raises(SystemExit):
        main(["eval", "--policy", "expert", "--camera-map", "top"])
    assert "POLICY_CAMERA=ENV_CAMERA" in capsys.readouterr().err
    assert main(["eval", "--policy", "expert", "--camera-map", MAP, "--episodes", "1"]) == 2
    assert "--camera-map (camera_map) applies to lerobot checkpoints, not to --policy " \
        "expert; drop it" in capsys.readouterr().err


def test_one_env_camera_for_two_policy_cameras_is_said_and_shown(ckpts, tmp_path, capsys):
    """front=side,side=side (a one-camera rig): allowed, with a note, and the summary states
    both policy cameras, not only the renamed one."""
    notes: list[str] = []
    mapping = resolve_camera_map(["front", "side"], parse_camera_map("front=side,side=side"),
                                 "ckpt", log=notes.append)
    assert mapping == {"front": "side", "side": "side"}
    assert notes == ["so101-sim eval: note: --camera-map feeds env camera side to policy "
                     "cameras front and side (the same image in each): fine for a one-camera "
                     "rig; otherwise map each policy camera to its own env camera"]
    assert describe_camera_map(mapping) == "policy front <- env side, policy side <- env side"
    assert describe_camera_map({"top": "front", "side": "side"}) == "policy top <- env front"

    task = short_task(tmp_path, max_steps=32)
    assert _eval(ckpts["front"], tmp_path / "one", task, "--episodes", "1",
                 "--camera-map", "front=side,side=side") == 0
    out = capsys.readouterr().out
    assert out.count("feeds env camera side to policy cameras front and side") == 1
    said = "cameras: policy front <- env side, policy side <- env side"
    assert said in out.strip().splitlines()[-1]  # the summary line
