"""LeRobot env plugin: makes ``--env.type=so101_pick_place`` build ``so101_sim/PickPlace-v0``.

Usage with lerobot 0.6.1. The ``lerobot_env_so101_sim`` distribution (``plugins/``, installed by
``make venv``) imports this module when any lerobot command starts, which registers the config
below with draccus before the command line is parsed; without it, add
``--env.discover_packages_path=so101_sim.lerobot_plugin``::

    lerobot-eval --env.type=so101_pick_place --env.task=pick_place \\
        --policy.path=outputs/train/.../pretrained_model --eval.n_episodes=50 --eval.batch_size=1

``--env.task`` is any task ``so101_sim.tasks.spec.load_task`` accepts (a name in envs/ or a TOML
path); ``fps`` and ``episode_length`` default to the task's, the cameras and frame size to the
camera inputs of a local ``--policy.path`` (else the task's cameras at 480x640;
``--env.cameras`` and ``--env.image_height/width`` choose). Under lerobot-train, the task,
cameras and frame size default to the dataset's (``so101_sim.dataset_reads``).

In Python, ``import so101_sim.lerobot_plugin`` and then
``lerobot.envs.factory.make_env(SO101PickPlaceEnvConfig(...), n_envs=1)``.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.envs.utils import NEW_ROLLOUT_OPTION
from lerobot.utils.constants import (
    ACTION,
    HF_LEROBOT_HOME,
    OBS_ENV_STATE,
    OBS_IMAGES,
    OBS_STATE,
)

from so101_sim import ENV_ID
from so101_sim.dataset_reads import DatasetReads, fine_tune_problem
from so101_sim.harness.trained_on import unseen_task_note
from so101_sim.policy_frames import (
    PolicyReads,
    env_input_problem,
    flag_value,
    missing_config_line,
    policy_frame_size,
    policy_path,
    refuse_or_warn,
    size_warning,
)
from so101_sim.sim import IMAGE_SIZE, OBS_TYPES, env_state_size
from so101_sim.sim.env_args import check_cameras
from so101_sim.tasks import ALL_CAMERAS, DEFAULT_TASK, load_task, loads_here
from so101_sim.train.checkpoint import TASK_KEY, demos_of
from so101_sim.utils.lerobot_cli import add_explainer, config_errors, one_line_errors, say
from so101_sim.utils.units import FEATURE_NAMES
from so101_sim.workers.local import start_fork_server

# lerobot 0.6.1's `load_plugin` lists the submodules of whatever `discover_packages_path`
# names through `module.__path__`, so a plain module raises AttributeError there. An empty
# `__path__` lets this module be named directly (it has no submodules to find).
__path__: list[str] = []

ENV_TYPE = "so101_pick_place"
ACTION_DIM = len(FEATURE_NAMES)
one_line_errors()  # a lerobot command given a bad --env.* value says so in one line
add_explainer(missing_config_line)  # and a --policy.path that is a run folder


@EnvConfig.register_subclass(ENV_TYPE)
@dataclass
class SO101PickPlaceEnvConfig(EnvConfig):
    """LeRobot config for the SO-101 pick-and-place env (see ``so101_sim.sim.env.PickPlaceEnv``).

    ``features`` are derived from ``obs_type`` and the image size in ``__post_init__`` so a
    policy built from this config (``make_policy(env_cfg=...)``) expects exactly what the env
    returns. ``fps`` and the episode cap are fixed by the task file; the fields exist because
    lerobot reads them, and they are checked against the task instead of silently disagreeing.
    """

    task: str | None = DEFAULT_TASK  # name in envs/ or path to a task TOML
    fps: int | None = None  # None: the task's [episode] fps (another value is refused)
    episode_length: int | None = None  # TimeLimit for lerobot-eval; None: the task's max_steps
    obs_type: str = "pixels_agent_pos"
    image_height: int = IMAGE_SIZE[0]  # default: the command line's policy's input size
    image_width: int = IMAGE_SIZE[1]
    # None: the cameras the command line's policy folder (or lerobot-train's dataset) reads
    # where the sim has them all, else the task's; e.g. --env.cameras='[front,side,wrist]'
    cameras: list[str] | None = None
    render_mode: str | None = "rgb_array"  # lerobot-eval renders videos through env.render()
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "environment_state": OBS_ENV_STATE,
            **{f"pixels/{cam}": f"{OBS_IMAGES}.{cam}" for cam in ALL_CAMERAS},
        }
    )

    def __post_init__(self) -> None:
        with config_errors(f"--env.type={ENV_TYPE}"):  # a lerobot command: one line
            self._settle()

    def _settle(self) -> None:
        """Check the fields, fill in the task's fps and episode cap, derive ``features``."""
        if self.obs_type not in OBS_TYPES:
            raise ValueError(f"obs_type={self.obs_type!r} is invalid; expected one of {OBS_TYPES}")
        if not self.task:
            raise ValueError(f"task={self.task!r} is invalid; expected a name in envs/ (e.g. "
                             "'pick_place') or a TOML path")
        if self.render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={self.render_mode!r} is invalid; expected "
                             "'rgb_array' or None (rendering is headless)")
        for name in ("image_height", "image_width"):
            if not 16 <= getattr(self, name) <= 2048:
                raise ValueError(f"{name}={getattr(self, name)} is invalid; expected 16..2048 "
                                 "pixels, e.g. --env.image_height=60 --env.image_width=80 (the "
                                 "shipped policy's input)")
        if self.cameras is not None:
            try:
                self.cameras = list(check_cameras(self.cameras))
            except ValueError:
                raise ValueError(f"cameras={self.cameras!r} is invalid; expected distinct names "
                                 f"from {', '.join(ALL_CAMERAS)}, e.g. "
                                 "--env.cameras='[front,side,wrist]'") from None
        found = policy_path(sys.argv)  # lerobot-eval's policy: it decides, as a dataset does
        demos = demos_of(found[0]) if found else {}  # for lerobot-train's, reads the dataset
        data = DatasetReads.of(sys.argv, HF_LEROBOT_HOME)  # lerobot-train's (None with a policy)
        taken = self._take_task(demos.get(TASK_KEY) if found else data.task if data else None)
        spec = load_task(self.task)
        if self.obs_type != "state":
            # lerobot-eval and lerobot-train's evaluation hand the policy these frames as they
            # are: left at the defaults, they would be the wrong picture (or a missing camera)
            # for any policy trained on other ones
            taken += self._take_cameras(spec.cameras, data)
            if (self.image_height, self.image_width) == IMAGE_SIZE:
                sized = policy_frame_size(sys.argv, self.cameras or spec.cameras)
                size = sized[0] if sized else data.frame_size(sys.argv) if data else None
                if size is not None and size != IMAGE_SIZE:
                    self.image_height, self.image_width = size
                    taken.append(f"{size[0]}x{size[1]} frames")
        # what came from the policy is said when the envs are built, with this note
        self._policy, self._policy_took = (found[0], taken) if found else (None, [])
        self._unseen_task = (unseen_task_note(found[0], [self.task], "--env.task", demos)
                             if found else None)
        if data is not None:
            self._tell_dataset(data, taken, spec)
        elif problem := fine_tune_problem(sys.argv, HF_LEROBOT_HOME):
            say(__name__, logging.WARNING, f"--env.type={ENV_TYPE}: {problem}")
        self.fps = spec.fps if self.fps is None else self.fps
        self.episode_length = (spec.max_steps if self.episode_length is None
                               else self.episode_length)
        if self.fps != spec.fps:
            raise ValueError(f"fps={self.fps} but task {spec.name!r} runs at {spec.fps} Hz; the "
                             f"control rate comes from the task file, pass --env.fps={spec.fps}")
        if not 1 <= self.episode_length <= spec.max_steps:
            raise ValueError(f"episode_length={self.episode_length} is invalid; the env ends "
                             f"episodes of task {spec.name!r} at max_steps={spec.max_steps}, so "
                             f"expected 1..{spec.max_steps} (raise max_steps in the task file)")
        self.features = self._derived_features()

    def _take_task(self, task: str | None) -> list[str]:
        """`task` (of the demos of the line's policy folder, as ``so101-sim eval`` takes, else
        of lerobot-train's dataset) where the line names none, if it loads here."""
        if (not isinstance(task, str) or self.task != DEFAULT_TASK or task == self.task
                or flag_value(sys.argv, "--env.task") is not None):
            return []  # a task chosen on the line, or in Python (hub_env's SO101_TASK)
        if not loads_here(task):
            return []  # a task file that moved: the dataset's warning says which it was
        self.task = task
        return [f"task {task}"]

    def _take_cameras(self, task_cameras: tuple[str, ...], data: DatasetReads | None
                      ) -> list[str]:
        """Where no cameras are given: those the line's policy folder (else dataset) reads,
        when the sim has them all and they are not the task's."""
        if self.cameras is not None:
            return []
        reads = PolicyReads.of(sys.argv)
        wanted = reads.cameras if reads else tuple(data.sizes) if data else ()
        if not wanted or wanted == task_cameras or not set(wanted) <= set(ALL_CAMERAS):
            return []
        self.cameras = list(wanted)
        return [f"cameras {', '.join(wanted)}"]

    def _tell_dataset(self, data: DatasetReads, taken: list[str], spec: Any) -> None:
        """One line for what came from lerobot-train's dataset, one per thing that differs
        from it (an error for a camera a diffusion or ACT policy would miss): said while the
        command line is parsed, before any training."""
        if taken:
            say(__name__, logging.INFO,
                f"--env.type={ENV_TYPE}: {', '.join(taken)}, as in dataset {data.root}, so that "
                "the policy trained on it is evaluated on what it learns from (--env.task, "
                "--env.cameras, --env.image_height and --env.image_width choose others)")
        cameras = [] if self.obs_type == "state" else self.cameras or list(spec.cameras)
        for problem in data.mismatches(sys.argv, self.task, cameras,
                                       (self.image_height, self.image_width)):
            refuse_or_warn(problem, f"--env.type={ENV_TYPE}", lambda text: say(
                __name__, logging.WARNING, f"--env.type={ENV_TYPE}: {text}"))

    def _derived_features(self) -> dict[str, PolicyFeature]:
        """Raw env keys (channel-last images, as the env returns them) -> PolicyFeature; the
        task file decides the cameras and the size of environment_state."""
        spec = load_task(self.task)
        feats = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(ACTION_DIM,)),
        }
        if self.obs_type != "state":
            shape = (self.image_height, self.image_width, 3)
            for cam in self.cameras or spec.cameras:
                feats[f"pixels/{cam}"] = PolicyFeature(type=FeatureType.VISUAL, shape=shape)
        if self.obs_type != "pixels_agent_pos":
            feats["environment_state"] = PolicyFeature(
                type=FeatureType.ENV, shape=(env_state_size(spec),))
        return feats

    @property
    def package_name(self) -> str:
        """Module that registers the gym id (the default, ``gym_<type>``, does not exist)."""
        return "so101_sim"

    @property
    def gym_id(self) -> str:
        """Our single gym id; ``task`` selects the task spec, not the id as in gym_pusht."""
        return ENV_ID

    @property
    def gym_kwargs(self) -> dict[str, Any]:
        """``gym.make`` kwargs. ``max_episode_steps`` adds the TimeLimit whose
        ``_max_episode_steps`` lerobot-eval's rollout reads."""
        return {
            "task": self.task,
            "obs_type": self.obs_type,
            "image_size": (self.image_height, self.image_width),
            "render_mode": self.render_mode,
            "max_episode_steps": self.episode_length,
            **({"cameras": tuple(self.cameras)} if self.cameras else {}),
        }

    def create_envs(
        self, n_envs: int, use_async_envs: bool = False
    ) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        """``{type: {0: VectorEnv}}`` like the base class, with each env wrapped in
        ``LeRobotRolloutAdapter`` (the base class offers no hook for wrappers)."""
        if n_envs < 1:
            raise ValueError(f"n_envs={n_envs} is invalid; expected at least 1")
        cameras = [k.split("/", 1)[1] for k in self.features if k.startswith("pixels/")]
        self._check_inputs(cameras)
        if cameras or self.render_mode is not None:  # a GL backend that cannot work: one line
            from so101_sim.sim.rendering import select_gl_backend

            with config_errors(f"--env.type={ENV_TYPE}", (RuntimeError,)):
                select_gl_backend()  # chosen once here: the env workers inherit MUJOCO_GL
        if took := getattr(self, "_policy_took", None):
            self._say_once(logging.INFO, f"{', '.join(took)}, as {self._policy} was trained on "
                           "(lerobot-eval hands the policy the frames as they are; --env.task, "
                           "--env.cameras, --env.image_height and --env.image_width choose "
                           "others)")
        if note := getattr(self, "_unseen_task", None):
            self._say_once(logging.WARNING, note.removeprefix("note: "))
        warning = size_warning(sys.argv, (self.image_height, self.image_width), cameras, "--env")
        if warning:  # lerobot-eval hands the policy these frames as they are
            self._say_once(logging.WARNING, warning)
        make_one = partial(_make_wrapped_env, self.gym_id, self.disable_env_checker,
                           self.gym_kwargs)
        if use_async_envs and n_envs > 1:
            # The server imports the env and lerobot-eval's own module once for all workers
            # (each imported torch and lerobot itself before: workers.local.script_module);
            # workers import as this process does, not from the cwd.
            start_fork_server(("so101_sim.sim.env", __name__))
            vec: gym.vector.VectorEnv = gym.vector.AsyncVectorEnv(
                [make_one] * n_envs, context="forkserver",
                autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
        else:
            vec = gym.vector.SyncVectorEnv(
                [make_one] * n_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
        return {self.type: {0: vec}}

    def _check_inputs(self, cameras: list[str]) -> None:
        """Refuse (or warn, for a policy type that does without) a policy on the command line
        that reads an input these envs do not send, before any env is built."""
        refuse_or_warn(env_input_problem(sys.argv, cameras, self.obs_type),
                       f"--env.type={ENV_TYPE}", partial(self._say_once, logging.WARNING))

    def _say_once(self, level: int, text: str) -> None:
        """Log `text` the first time these envs are built: lerobot-train builds them again
        at every evaluation, and the line would not change."""
        said = self.__dict__.setdefault("_said", set())
        if text not in said:
            said.add(text)
            logging.getLogger(__name__).log(level, "--env.type=%s: %s", ENV_TYPE, text)


class LeRobotRolloutAdapter(gym.Wrapper):
    """Bridges two lerobot-eval conventions that ``PickPlaceEnv`` does not follow itself.

    * ``rollout()`` resets with ``options={NEW_ROLLOUT_OPTION: True}``; ``PickPlaceEnv``
      rejects unknown reset options (to catch typos), so that key is dropped here.
    * ``rollout()`` sets ``observation["task"]`` from ``task_description`` and otherwise
      from ``task``, which on ``PickPlaceEnv`` is a ``TaskSpec``, not the string language
      policies expect; ``task_description`` provides the task's description.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.task_description: str = env.unwrapped.task.description

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        kept = {k: v for k, v in (options or {}).items() if k != NEW_ROLLOUT_OPTION}
        return self.env.reset(seed=seed, options=kept or None)


def _make_wrapped_env(gym_id: str, disable_env_checker: bool,
                      gym_kwargs: dict[str, Any]) -> gym.Env:
    """Module-level (picklable) env factory for the vector envs."""
    env = gym.make(gym_id, disable_env_checker=disable_env_checker, **gym_kwargs)
    return LeRobotRolloutAdapter(env)


__all__ = ["ENV_TYPE", "LeRobotRolloutAdapter", "SO101PickPlaceEnvConfig"]
