"""Configs of the sim robot and its expert teleoperator, as lerobot's CLIs parse them.

lerobot builds the device from its config by name (``make_device_from_device_class``): the
config class ``XxxConfig`` of module ``lerobot_robot_so101_sim.config`` is turned into class
``Xxx`` looked up in the parent package, which exports ``SO101Sim`` and ``SO101SimExpert``.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

from lerobot.cameras import CameraConfig
from lerobot.robots.config import RobotConfig
from lerobot.teleoperators.config import TeleoperatorConfig
from lerobot.utils.constants import HF_LEROBOT_HOME

from so101_sim.dataset import noted_seeds
from so101_sim.dataset_reads import DatasetReads
from so101_sim.harness.trained_on import unseen_task_note
from so101_sim.policy_frames import (
    PolicyReads,
    flag_value,
    missing_config_line,
    policy_frame_size,
    policy_path,
)
from so101_sim.tasks import load_task, loads_here
from so101_sim.tasks.spec import ALL_CAMERAS
from so101_sim.train.checkpoint import TASK_KEY, demos_of, train_image_size
from so101_sim.utils.lerobot_cli import (
    add_explainer,
    command_name,
    config_errors,
    one_line_errors,
    say,
)

ROBOT_TYPE = "so101_sim"
RECORDERS = ("lerobot-record", "lerobot-rollout")  # the commands that write a dataset
TELEOP_TYPE = "so101_sim_expert"
EPISODE_END = ("auto", "reset", "hold")
_SIZE_RANGE = (16, 2048)
DEFAULT_IMAGE = (480, 640)
DEFAULT_TASK = "pick_place"  # the command line's policy may set another
one_line_errors()  # a lerobot command given a bad --robot.* value says so in one line
add_explainer(missing_config_line)  # and a --policy.path that is a run folder


@RobotConfig.register_subclass(ROBOT_TYPE)
@dataclass
class SO101SimConfig(RobotConfig):
    """``--robot.type=so101_sim``: the so101-sim MuJoCo arm with so101_follower's features."""

    # A task of the suite (pick_place, lift, stack, tidy, pick_place_anywhere, pick_place_dr)
    # or the path of a task TOML file.
    task: str = DEFAULT_TASK
    # Seed of the first episode; every later episode takes the next one.
    seed: int = 0
    # Cameras in the observations, e.g. [front,side,wrist]; empty: the task's own, or those the
    # command line's local policy reads where the sim has them all.
    camera_names: list[str] = field(default_factory=list)
    # Size of each camera image in the observations. Default: 480 x 640, or, when the command
    # line names a local policy (--policy.path, --pretrained_name_or_path) and sets no image or
    # render size, that policy's input size, rendered at its demos' size and resized.
    image_height: int = DEFAULT_IMAGE[0]
    image_width: int = DEFAULT_IMAGE[1]
    # Render at this size and resize to image_height x image_width with so101-sim's training
    # resize (so101_sim.utils.image_pipeline.resize_frames); 0: render at the image size.
    # 480 x 640 with 60 x 80 images feeds the shipped policy as `so101-sim eval --faithful` does.
    render_height: int = 0
    render_width: int = 0
    # Mesh detail of this image width (0: the render width's), as so101-sim eval's reduced path.
    mesh_width: int = 0
    # Pace send_action at the task's fps (30 Hz), as a real arm moves; false: as fast as the
    # caller calls it.
    realtime: bool = True
    # What follows the end of an episode: "reset" starts the next seed at once; "hold" freezes
    # the last frame until lerobot saves (next seed) or discards (same seed again) its dataset
    # episode; "auto" holds while the episode is being recorded into a dataset, else resets.
    episode_end: str = "auto"
    # End the command, as Ctrl-C does, once this many episodes have ended (0: never).
    episodes: int = 0
    # Append each episode's outcome to this JSON-lines file (for scripts around the CLIs).
    outcomes_path: Path | None = None
    # The robot client's policy server is `python -m lerobot_robot_so101_sim.patched_server`,
    # which serves a Diffusion Policy; false: the client asking for one is refused at connect,
    # since lerobot's own server fails its every chunk (lerobot issue #3861).
    patched_server: bool = False
    # Not read: the sim renders its own cameras (camera_names). Declared so that a real
    # SO-101's `--robot.cameras='{laptop: {type: opencv, ...}}'` gets the flags to use instead
    # of draccus's "The fields `cameras` are not valid for SO101SimConfig".
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
    # Not read: the real arm's serial port (a field it requires), so that its command line
    # runs with only --robot.type changed; one line says it is not used.
    port: str | None = None

    def __post_init__(self) -> None:
        with config_errors(f"--robot.type={ROBOT_TYPE}"):  # a lerobot command: one line
            if self.cameras:  # before the base class asks each real camera for its fps
                named = [c for c in self.cameras if c in ALL_CAMERAS] or ["front", "side"]
                raise ValueError(
                    f"--robot.cameras configures real cameras ({', '.join(self.cameras)}); the "
                    f"sim renders its own: pass --robot.camera_names='[{','.join(named)}]' "
                    f"(from {', '.join(ALL_CAMERAS)}) and --robot.image_height / "
                    "--robot.image_width for their size")
            super().__post_init__()
            self._check()
        if self.port:
            say(__name__, logging.INFO, f"--robot.type={ROBOT_TYPE}: --robot.port={self.port} is "
                "not used (the sim has no motor bus)")

    def _check(self) -> None:
        self.task_by: Path | None = None  # the policy whose demos' task the robot took
        self.dataset_note = ""  # what the robot took from the line's dataset
        episode = flag_value(sys.argv, "--dataset.episode")
        data = DatasetReads.at(sys.argv, HF_LEROBOT_HOME) if episode is not None else None
        if data is not None and episode.isdigit():
            self._take_replayed(data, int(episode))
        elif (command_name(sys.argv[0] if sys.argv else "") in RECORDERS
              and str(flag_value(sys.argv, "--resume")).lower() in ("true", "1", "yes")
              and flag_value(sys.argv, "--robot.seed") is None):
            self._seed_after(DatasetReads.at(sys.argv, HF_LEROBOT_HOME))
        found = policy_path(sys.argv)
        demos = demos_of(found[0]) if found else {}  # for lerobot-train's, reads the dataset
        trained = demos.get(TASK_KEY)
        if (isinstance(trained, str) and self.task == DEFAULT_TASK != trained
                and flag_value(sys.argv, "--robot.task") is None and loads_here(trained)):
            self.task, self.task_by = trained, found[0]
        elif found and (note := unseen_task_note(found[0], [self.task], "--robot.task", demos)):
            say(__name__, logging.WARNING,
                f"--robot.type={ROBOT_TYPE}: {note.removeprefix('note: ')}")
        try:
            task = load_task(self.task)
        except ValueError as exc:
            raise ValueError(f"--robot.task={self.task!r} is invalid: {exc}") from exc
        names = tuple(self.camera_names) or tuple(task.cameras)
        if len(set(names)) != len(names) or any(c not in ALL_CAMERAS for c in names):
            raise ValueError(f"--robot.camera_names={list(names)} is invalid; expected distinct "
                             f"names from {list(ALL_CAMERAS)}, e.g. "
                             "--robot.camera_names='[front,side]' (empty: the task's)")
        self.cameras_by: Path | None = None  # the policy whose cameras the robot took
        reads = None if self.camera_names else PolicyReads.of(sys.argv)
        if reads and reads.cameras and reads.cameras != names and set(reads.cameras) <= set(
                ALL_CAMERAS):  # lerobot would hand the policy only the cameras the robot has
            self.camera_names, self.cameras_by = list(reads.cameras), reads.policy
            names = reads.cameras
        out = self.outcomes_path
        if out is not None and (Path(out).is_dir() or any(p.is_file() for p in Path(out).parents)):
            raise ValueError(f"--robot.outcomes_path={str(out)!r} is invalid: it is a folder or "
                             "lies under a file; expected the path of a JSON-lines file, e.g. "
                             "--robot.outcomes_path=data/outcomes.jsonl")
        if self.episode_end not in EPISODE_END:
            raise ValueError(f"--robot.episode_end={self.episode_end!r} is invalid; expected "
                             f"one of {EPISODE_END}, e.g. --robot.episode_end=hold")
        for name in ("seed", "episodes", "mesh_width"):
            if getattr(self, name) < 0:
                raise ValueError(f"--robot.{name}={getattr(self, name)} is invalid; expected an "
                                 "integer >= 0")
        lo, hi = _SIZE_RANGE
        for name in ("image_height", "image_width"):
            if not lo <= getattr(self, name) <= hi:
                raise ValueError(f"--robot.{name}={getattr(self, name)} is invalid; expected "
                                 f"{lo}..{hi} pixels, e.g. --robot.image_height=60 "
                                 "--robot.image_width=80")
        render = (self.render_height, self.render_width)
        if render != (0, 0) and not all(lo <= v <= hi for v in render):
            raise ValueError(f"--robot.render_height/width={render[0]}x{render[1]} is invalid; "
                             f"expected both 0 (render at the image size) or both {lo}..{hi}, "
                             "e.g. --robot.render_height=480 --robot.render_width=640")
        self.sized_by: Path | None = None  # the policy whose input size the images took
        if self.image_size == DEFAULT_IMAGE and render == (0, 0):
            self._size_for_policy(names)
        if (command_name(sys.argv[0] if sys.argv else "") in RECORDERS
                and flag_value(sys.argv, "--dataset.repo_id") is not None
                and flag_value(sys.argv, "--dataset.single_task") is None):
            # lerobot then stores an empty task text: nothing for a language-conditioned policy,
            # and so101-sim train cannot tell which task the demos are of
            say(__name__, logging.WARNING, f"--robot.type={ROBOT_TYPE}: no "
                "--dataset.single_task, so every frame's task text is empty; add "
                f"--dataset.single_task=\"{task.description}\" (task {task.name})")

    def _size_for_policy(self, cameras: tuple[str, ...]) -> None:
        """The frames the command line's policy takes: lerobot hands it the robot's as they
        are, so the default 480 x 640 would be the wrong picture for a 60 x 80 policy."""
        found = policy_frame_size(sys.argv, cameras, "--robot")
        if found is None or found[0] == DEFAULT_IMAGE:
            return
        (self.image_height, self.image_width), self.sized_by = found
        try:
            render = train_image_size(found[1])
        except (OSError, ValueError):
            render = None  # an unreadable training record: render at the image size
        if render is not None and render != found[0]:
            self.render_height, self.render_width = render

    def _take_replayed(self, data: DatasetReads, episode: int) -> None:
        """lerobot-replay of a so101-sim recording: the episode's seed and the recording's task
        where the line gives none (on another seed the replayed actions miss the cube)."""
        seed = data.episode_seed(episode) if flag_value(sys.argv, "--robot.seed") is None else None
        task = data.task if (self.task == DEFAULT_TASK != data.task and data.task is not None
                             and flag_value(sys.argv, "--robot.task") is None
                             and loads_here(data.task)) else None
        took = [(f"task {task}", "--robot.task")] if task else []
        took += [(f"seed {seed}", "--robot.seed")] if seed is not None else []
        if not took:
            return
        self.task, self.seed = task or self.task, self.seed if seed is None else seed
        self.dataset_note = (f"; {' and '.join(w for w, _ in took)} of episode {episode} of "
                            f"dataset {data.root} ({' and '.join(f for _, f in took)} "
                            f"choose{'s' if len(took) == 1 else ''} others)")

    def _seed_after(self, data: DatasetReads | None) -> None:
        """lerobot-record (or -rollout) --resume=true adds episodes to a dataset: they start
        after the seeds its episodes ran (the robot's notes), not at seed 0 again, which
        recorded the same scenes twice."""
        seeds = noted_seeds(data.root) if data is not None else None
        if seeds:
            self.seed = max(seeds) + 1
            self.dataset_note = (f"; seed {self.seed} on, after the seeds of the "
                                 f"{len(seeds)} episodes dataset {data.root} holds "
                                 "(--robot.seed chooses others)")

    def connect_note(self) -> str:
        """The connect line's note on the frames' size and what the robot took from the line's
        policy or dataset."""
        note = "" if self.render_size == self.image_size else (
            f" (rendered at {self.render_size[0]}x{self.render_size[1]}, resized with "
            "so101_sim's resize_frames)")
        if getattr(self, "sized_by", None) is not None:  # said, as the flags would have been
            note += (f", the input size of {self.sized_by} (--robot.image_height/width and "
                     "render_height/width choose others)")
        return note + self.taken_note()

    def taken_note(self) -> str:
        """The connect line's note on what the robot took from the line's policy or dataset."""
        took = [(what, flag) for what, flag, by in (
            ("task", "--robot.task", self.task_by),
            ("cameras", "--robot.camera_names", self.cameras_by)) if by is not None]
        if not took:
            return self.dataset_note
        return (f"; {' and '.join(w for w, _ in took)} as {self.task_by or self.cameras_by} was "
                f"trained on ({' and '.join(f for _, f in took)} choose"
                f"{'s' if len(took) == 1 else ''} others){self.dataset_note}")

    @property
    def image_size(self) -> tuple[int, int]:
        return self.image_height, self.image_width

    @property
    def render_size(self) -> tuple[int, int]:
        """Where the cameras render: the image size unless a render size is given."""
        if self.render_height:
            return self.render_height, self.render_width
        return self.image_size


@TeleoperatorConfig.register_subclass(TELEOP_TYPE)
@dataclass
class SO101SimExpertConfig(TeleoperatorConfig):
    """``--teleop.type=so101_sim_expert``: so101-sim's scripted expert at the controls of the
    so101_sim robot connected in the same process."""

    # --robot.id of the sim robot to drive; empty: the one so101_sim robot connected.
    robot_id: str | None = None
    # Retry a missed grasp, a dropped cube or a cube left off the target (so101-sim record's
    # --recover).
    recover: bool = False
