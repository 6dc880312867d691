"""What to say when the policy on a lerobot command line takes inputs the sim does not send:
frames of another size (one warning), or a camera or the environment state the sim does not
send (an error for the policy types that would stop at their first step, else a warning); and
when it is no policy folder, or a type lerobot's async server cannot run (an error).

lerobot-eval and lerobot-rollout with ``--policy.path`` (0.6.1's lerobot-record takes none)
and the async robot client build the policy apart from the env or robot, and neither lerobot
nor the policy's processors resize camera frames: the shipped 60x80 policy given the default
480x640 frames centre-crops 54x72 out of their middle and fails every episode without a word.
The env and the robot cannot see the policy, so they read its path from the command line and
its ``config.json`` (as data): given no size, they send the policy's (``policy_frame_size``);
given another, they warn with the flags that fit. A hub id or an unreadable folder is left
alone. Imports neither torch nor lerobot.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from shlex import quote

from so101_sim.tasks import ALL_CAMERAS
from so101_sim.train.checkpoint import (
    image_input_shapes,
    nearby_policies,
    other_kind,
    train_image_size,
)
from so101_sim.utils.lerobot_cli import causes, config_errors

POLICY_FLAGS = ("--policy.path", "--pretrained_name_or_path")  # lerobot CLIs, robot_client
# lerobot 0.6 policy types whose forward indexes every image input they were trained on, so a
# camera the sim does not send is a KeyError at the first step (modeling_act.py,
# modeling_diffusion.py, modeling_multi_task_dit.py); pi0 and smolvla pad a missing camera with
# an empty image instead.
EVERY_CAMERA_TYPES = frozenset({"act", "diffusion", "multi_task_dit"})
ENV_STATE = "observation.environment_state"


# lerobot 0.6.1's async policy server calls predict_action_chunk on one observation at a time
# and never fills the observation queues select_action keeps, which these types'
# predict_action_chunk reads: every chunk fails on the server (AssertionError, or "stack
# expects a non-empty TensorList"; lerobot issue #3861), logged there with no traceback, and
# the robot client waits for actions for ever.
SERVER_FAILS_TYPES = frozenset({"diffusion", "tdmpc", "vqbet"})


def flag_value(argv: Sequence[str], flag: str) -> str | None:
    """The value of `flag` on a command line (``FLAG=V`` or ``FLAG V``), if given."""
    for i, word in enumerate(argv):
        if word.startswith(flag + "="):
            return word.split("=", 1)[1]
        if word == flag and i + 1 < len(argv):
            return argv[i + 1]
    return None


def policy_path(argv: Sequence[str]) -> tuple[Path, str] | None:
    """The local policy folder named on a lerobot command line and its flag, if any."""
    for flag in POLICY_FLAGS:
        value = flag_value(argv, flag)
        if value and (Path(value).expanduser() / "config.json").is_file():
            return Path(value).expanduser(), flag
    return None


def sets_frame_size(argv: Sequence[str], group: str = "--env") -> bool:
    """Whether a lerobot command line chooses the frame size itself: ``{group}.image_height``,
    ``image_width``, ``render_height`` or ``render_width``, or a ``--config_path`` that could."""
    chosen = ("--config_path", *(f"{group}.{name}" for name in (
        "image_height", "image_width", "render_height", "render_width")))
    return any(word.split("=", 1)[0] in chosen for word in argv)


def policy_frame_size(argv: Sequence[str], cameras: Sequence[str],
                      group: str = "--env") -> tuple[tuple[int, int], Path] | None:
    """The one size of the camera inputs of the local policy a lerobot command line names, and
    its folder, where that line sets no frame size itself (``sets_frame_size``): the frame
    size that env or robot should send. None where the line chooses, names
    no readable policy, or the policy's cameras differ in size."""
    if sets_frame_size(argv, group):
        return None
    found = policy_path(argv)
    if found is None:
        return None
    try:
        sizes = {tuple(shape[1:3]) for cam, shape in image_input_shapes(found[0]).items()
                 if cam in cameras}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None  # not a checkpoint config we can read: loading it will say so
    if len(sizes) != 1:
        return None
    h, w = sizes.pop()
    return (int(h), int(w)), found[0]


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
class InputProblem:
    """A policy input the sim does not send: `text` names it and the fix in one line; `fatal`
    when the policy's type reads every input it was trained on (its first step would fail)."""

    text: str
    fatal: bool


@dataclass(frozen=True)
class PolicyReads:
    """What the local policy on a lerobot command line reads, from its config.json (as data)."""

    policy: Path
    cameras: tuple[str, ...]  # in its config's order
    env_state: bool  # observation.environment_state
    fatal: bool  # its type is one of EVERY_CAMERA_TYPES

    @classmethod
    def of(cls, argv: Sequence[str]) -> PolicyReads | None:
        """None without a local policy folder, or for one whose config we cannot read."""
        found = policy_path(argv)
        if found is None:
            return None
        try:
            config = json.loads((found[0] / "config.json").read_text(encoding="utf-8"))
            cameras = tuple(image_input_shapes(found[0]))
            env_state = ENV_STATE in config["input_features"]
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return None  # not a checkpoint config we can read: loading it will say so
        return cls(found[0], cameras, env_state, config.get("type") in EVERY_CAMERA_TYPES)

    def problem(self, missing: Sequence[str], sender: str, sent: str, fix: str) -> InputProblem:
        """The InputProblem for `missing` inputs (camera names or ENV_STATE)."""
        if list(missing) == [ENV_STATE]:
            needs = f"{ENV_STATE} (the cube's and target's poses)"
            key = ENV_STATE
        else:
            needs = f"camera{'s' if len(missing) > 1 else ''} {', '.join(missing)}"
            if tuple(missing) != self.cameras:
                needs += f" (it reads {', '.join(self.cameras)})"
            key = f"observation.images.{missing[0]}"
        fate = (f"its first step would stop with KeyError '{key}'" if self.fatal else
                "lerobot would run it without that input" if key == ENV_STATE else
                "lerobot would feed it an empty image for each")
        return InputProblem(f"{self.policy} needs {needs}, and this {sender} sends {sent}: "
                            f"{fate}; {fix}", self.fatal)


def refuse_or_warn(problem: InputProblem | None, flags: str,
                   warn: Callable[[str], None]) -> None:
    """A fatal `problem` raised as the one-line error of `flags` (e.g. --env.type=X); any other
    handed to `warn`."""
    if problem is None:
        return
    if problem.fatal:
        with config_errors(flags):
            raise ValueError(problem.text)
    warn(problem.text)


def _eval_fix(reads: PolicyReads, missing: Sequence[str]) -> str:
    other = [cam for cam in missing if cam not in ALL_CAMERAS]
    return (f"`so101-sim eval --policy {quote(str(reads.policy))}` renders any of "
            f"{', '.join(ALL_CAMERAS)}"
            + (f" and maps other names with --camera-map, e.g. --camera-map {other[0]}=front"
               if other else ""))


def folder_problem(argv: Sequence[str]) -> InputProblem | None:
    """A local folder given as the policy that holds no config.json: a training run (its
    policy inside it), a folder of policies, a dataset or an evaluation. lerobot-eval and
    lerobot-rollout stop on it with a traceback while they parse the command line ("config.json
    not found in ..."); the robot client's server fails to load it. None for the rest."""
    for flag in POLICY_FLAGS:
        value = flag_value(argv, flag)
        folder = Path(value).expanduser() if value else None
        if folder is None or not folder.is_dir() or (folder / "config.json").is_file():
            continue
        near = nearby_policies(folder)
        why = (" (so101-sim train keeps its final policy in RUN/pretrained_model, lerobot-train "
               "in checkpoints/last/pretrained_model)"
               if near and near[0].name == "pretrained_model" else "")
        what = (f"did you mean {' or '.join(f'{flag}={p}' for p in near)}?{why}" if near else
                other_kind(folder).removesuffix("; ") or
                "expected a policy checkpoint folder (config.json, model.safetensors)")
        return InputProblem(f"{flag}={value} holds no config.json, so lerobot cannot load a "
                            f"policy from it; {what}", True)
    return None


def missing_config_line(exc: BaseException) -> str | None:
    """For lerobot's ``FileNotFoundError: config.json not found in FOLDER``, raised while a
    command line is parsed (before any env or robot exists): ``folder_problem``'s line."""
    if not any(isinstance(e, FileNotFoundError) and "config.json" in str(e)
               for e in causes(exc)):
        return None
    problem = folder_problem(sys.argv)
    return problem.text if problem is not None else None


def env_input_problem(argv: Sequence[str], cameras: Sequence[str],
                      obs_type: str) -> InputProblem | None:
    """What lerobot-eval's envs (`--env.obs_type`, `cameras`) fail to send the local policy on
    `argv`, or None."""
    reads = PolicyReads.of(argv)
    if reads is None:
        return None
    sent = ", ".join(cameras) or "no camera frames"
    if missing := [cam for cam in reads.cameras if cam not in cameras]:
        # with neither flag, the env sends the cameras the policy reads where the sim has them
        fix = (_eval_fix(reads, missing) if not set(reads.cameras) <= set(ALL_CAMERAS) else
               f"drop --env.obs_type={obs_type} (the default, pixels_agent_pos, sends "
               f"{', '.join(reads.cameras)})" if obs_type == "state" else
               "drop --env.cameras (the env then sends the cameras the policy reads)")
        return reads.problem(missing, "env", sent, fix)
    if reads.env_state and obs_type == "pixels_agent_pos":
        return reads.problem([ENV_STATE], "env", f"{sent} and the joints",
                             "add --env.obs_type=pixels_agent_pos_env_state")
    return None


def async_server_problem(argv: Sequence[str],
                         patched_server: bool = False) -> InputProblem | None:
    """The robot client asking lerobot's policy server for a type it cannot serve, or None.
    `patched_server`: the client talks to ``lerobot_robot_so101_sim.patched_server``, which
    serves diffusion (only)."""
    kind, path = flag_value(argv, "--policy_type"), flag_value(argv, "--pretrained_name_or_path")
    if path is None or kind not in SERVER_FAILS_TYPES or (patched_server and kind == "diffusion"):
        return None
    from so101_sim.utils.versions import installed

    return InputProblem(
        f"--policy_type={kind}: lerobot {installed('lerobot')}'s policy server"
        + (" (patched for diffusion only)" if patched_server else "")
        + f" calls predict_action_chunk on one observation, without the observation history a "
        f"{kind} policy keeps, so every chunk fails on the server (lerobot issue #3861) and the "
        "arm never moves; run it in one process instead: lerobot-rollout --strategy.type=base "
        f"{quote(f'--policy.path={path}')} --robot.type=so101_sim, or so101-sim eval --policy "
        f"{quote(str(path))}"
        + ("; or serve it with python -m lerobot_robot_so101_sim.patched_server (lerobot's "
           "server and flags, fixed for diffusion) and add --robot.patched_server=true"
           if kind == "diffusion" else ""), True)


def robot_input_problem(argv: Sequence[str], cameras: Sequence[str],
                        patched_server: bool = False) -> InputProblem | None:
    """What the sim robot (`--robot.camera_names` = `cameras`) fails to send the local policy on
    `argv` (or the robot client's policy server fails to run for it: `patched_server` as in
    ``async_server_problem``), or None."""
    if (problem := async_server_problem(argv, patched_server)
            or folder_problem(argv)) is not None:
        return problem
    reads = PolicyReads.of(argv)
    if reads is None:
        return None
    sent = ", ".join(cameras)
    if missing := [cam for cam in reads.cameras if cam not in cameras]:
        fix = (f"add --robot.camera_names='[{','.join(reads.cameras)}]'"
               if set(reads.cameras) <= set(ALL_CAMERAS) else
               f"the sim's cameras are {', '.join(ALL_CAMERAS)}; " + _eval_fix(reads, missing))
        return reads.problem(missing, "robot", sent, fix)
    if reads.env_state:
        return reads.problem([ENV_STATE], "robot", f"{sent} and the joints, as the real arm does",
                             "evaluate it in the env: `so101-sim eval --policy "
                             f"{reads.policy}`, or lerobot-eval with "
                             "--env.obs_type=pixels_agent_pos_env_state")
    return None
