"""What to say when the policy on a lerobot command line takes frames the sim does not send:
frames of another size (one warning), or a camera the sim does not send (an error for the
policy types that would stop at their first step, else a warning).

lerobot-eval, lerobot-rollout, lerobot-record with ``--policy.path`` and the async robot
client build the policy apart from the env or robot, and neither lerobot nor the policy's
processors resize camera frames: the shipped 60x80 policy given the default 480x640 frames
centre-crops 54x72 out of their middle and fails every episode without a word. The env and the
robot cannot see the policy, so they read its path from the command line and its
``config.json`` (as data), and name the flags that fit. A hub id or an unreadable folder is
left alone. Imports neither torch nor lerobot.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from so101_sim.train.checkpoint import image_input_shapes, train_image_size

POLICY_FLAGS = ("--policy.path", "--pretrained_name_or_path")  # lerobot CLIs, robot_client
# lerobot 0.6 policy types whose forward indexes every image input they were trained on, so a
# camera the sim does not send is a KeyError at the first step (modeling_act.py,
# modeling_diffusion.py, modeling_multi_task_dit.py); pi0 and smolvla pad a missing camera with
# an empty image instead.
EVERY_CAMERA_TYPES = frozenset({"act", "diffusion", "multi_task_dit"})


def policy_path(argv: Sequence[str]) -> tuple[Path, str] | None:
    """The local policy folder named on a lerobot command line and its flag, if any."""
    for i, word in enumerate(argv):
        for flag in POLICY_FLAGS:
            value = (word.split("=", 1)[1] if word.startswith(flag + "=")
                     else argv[i + 1] if word == flag and i + 1 < len(argv) else None)
            if value and (Path(value).expanduser() / "config.json").is_file():
                return Path(value).expanduser(), flag
    return None


def size_warning(argv: Sequence[str], image_size: tuple[int, int], cameras: Sequence[str],
                 group: str = "--robot") -> str | None:
    """The warning for a policy whose image inputs are not `image_size`, else None. `group`
    names the flags: ``--robot`` (which can also render larger and resize) or ``--env``."""
    found = policy_path(argv)
    if found is None:
        return None
    policy, flag = found
    try:
        sizes = {cam: shape[1:3] for cam, shape in image_input_shapes(policy).items()
                 if cam in cameras}
        render = train_image_size(policy)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None  # not a checkpoint config we can read: loading it will say so
    wrong = {cam: hw for cam, hw in sizes.items() if hw != tuple(image_size)}
    if not wrong:
        return None
    h, w = next(iter(wrong.values()))
    flags = f"{group}.image_height={h} {group}.image_width={w}"
    if group == "--robot" and render is not None and render != (h, w):  # render as its demos
        flags += f" --robot.render_height={render[0]} --robot.render_width={render[1]}"
    shown = ", ".join(f"{cam} {hh}x{ww}" for cam, (hh, ww) in wrong.items())
    fate = ("the policy server resizes them by plain bilinear interpolation, not as the demos "
            "were resized" if flag == "--pretrained_name_or_path" else
            "nothing on the way resizes them, so the policy would see the wrong picture")
    sender = "robot" if group == "--robot" else "env"
    return (f"{policy} takes camera frames of {shown}, and this {sender} sends "
            f"{image_size[0]}x{image_size[1]}: {fate}; add {flags}")


@dataclass(frozen=True)
class CameraGap:
    """A local policy on the command line reads cameras the sim does not send."""

    policy: Path
    reads: tuple[str, ...]  # the policy's cameras, in its config's order
    missing: tuple[str, ...]  # those the sim does not send
    fatal: bool  # its type reads every camera (EVERY_CAMERA_TYPES): the first step would fail

    def message(self, sender: str, sends: Sequence[str], fix: str) -> str:
        """One line: what the policy reads, what the `sender` ("env", "robot") sends, the fix."""
        sent = ", ".join(sends) if sends else "no camera frames"
        needs = f"camera{'s' if len(self.missing) > 1 else ''} {', '.join(self.missing)}"
        if self.missing != self.reads:
            needs += f" (it reads {', '.join(self.reads)})"
        fate = (f"its first step would stop with KeyError 'observation.images.{self.missing[0]}'"
                if self.fatal else "lerobot would feed it an empty image for each")
        return f"{self.policy} needs {needs}, and this {sender} sends {sent}: {fate}; {fix}"


def camera_gap(argv: Sequence[str], cameras: Sequence[str]) -> CameraGap | None:
    """The CameraGap of the local policy named on `argv` against the `cameras` sent, else None
    (no local policy, one we cannot read, or every camera it reads is sent)."""
    found = policy_path(argv)
    if found is None:
        return None
    policy = found[0]
    try:
        reads = tuple(image_input_shapes(policy))
        kind = json.loads((policy / "config.json").read_text(encoding="utf-8")).get("type")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None  # not a checkpoint config we can read: loading it will say so
    missing = tuple(cam for cam in reads if cam not in cameras)
    if not missing:
        return None
    return CameraGap(policy, reads, missing, kind in EVERY_CAMERA_TYPES)
