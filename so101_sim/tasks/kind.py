"""The task-kind registry: what one kind of task adds to the common scene and episode.

A task file's ``kind`` names a ``TaskKind``; every part of the pipeline asks the kind, never
the kind's name: layout sampling, the objects added to the scene, the goal, the success
tracker and its failure modes, the ``environment_state`` layout and the scripted expert's
plan. The suite's kinds are ``pick_place``, ``lift``, ``stack`` and ``tidy`` (one file each
in this package). A new kind is a subclass registered from your own code::

    from so101_sim.tasks import TaskKind, register_kind

    @register_kind
    class Shelf(TaskKind):
        name = "shelf"
        ...

Task files stay data: a TOML file can only name a kind that Python code registered.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from so101_sim.tasks.layouts import MAX_DRAWS, Layout, all_separated, draw_cubes, in_reach

if TYPE_CHECKING:
    import mujoco

    from so101_sim.tasks import TaskSpec

#: environment_state: first cube position (3) + quaternion wxyz (4) + goal position (3)
ENV_STATE_BASE = 10
COMMON_FAILURES = ("never_grasped", "dropped", "misplaced", "timeout", "sim_unstable")


class Tracker(Protocol):
    """Follows one episode: ``update`` after every step, ``failure_mode`` at a failed end."""

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]: ...

    def failure_mode(self, env: Any) -> str: ...


@dataclass
class PlanContext:
    """What a kind may use to change the scripted expert's plan (``TaskKind.expert_plan``).

    ``ik``: the expert's ``TopDownIK``; ``grasp``: tool position at the grasp (m); ``yaw``:
    jaw yaw (rad); ``q_grasp``: joint radians (5,) there; ``carry_height``: this episode's
    carry height (m); ``act(q5, gripper)``: joint radians -> an action in LeRobot units;
    ``closed``/``opened``: the gripper commands the expert uses.
    """

    ik: Any
    grasp: np.ndarray
    yaw: float
    q_grasp: np.ndarray
    carry_height: float
    act: Callable[[np.ndarray, float], np.ndarray]
    closed: float
    opened: float


Segment = tuple[str, int, np.ndarray]  # (phase name, control steps, target action)


class TaskKind:
    """Base class of a task kind; override what your kind does differently.

    Defaults describe a one-cube pick-and-place onto the ``target`` mocap body. Methods take
    the ``TaskSpec`` (the parsed task file) and, for the env-facing ones, the env: read it
    through its public helpers (``cube_pos``, ``cube_speed``, ``cube_contacts``,
    ``pad_clearance``, ``goal_pos``, ``cube_half``, ``data``, ``ids``).
    """

    #: The ``kind`` a task file names.
    name: ClassVar[str] = ""
    #: Every ``info["failure_mode"]`` the tracker can give, ``sim_unstable`` included.
    failure_modes: ClassVar[tuple[str, ...]] = COMMON_FAILURES
    #: TaskSpec fields a task file of this kind may leave out (sections the kind ignores).
    spec_defaults: ClassVar[dict[str, Any]] = {}
    #: Most cubes a task file may ask for (``[box] cubes``).
    max_cubes: ClassVar[int] = 1
    #: The place is on or among other objects (stack's base cube, tidy's box): the expert
    #: carries clear above it, re-aims as the lowering starts and retreats straight up.
    place_among_objects: ClassVar[bool] = False
    #: The expert retries a cube left off the goal once its plan ran out (``recover=True``).
    retry_misplaced: ClassVar[bool] = False

    # ------------------------------------------------------------------ task file
    def check(self, spec: TaskSpec, source: str) -> str | None:
        """A message naming the bad key and value if `spec` is invalid for this kind."""
        return None

    # ------------------------------------------------------------------ layout
    def draw(self, spec: TaskSpec, rng: np.random.Generator) -> Layout:
        """One draw of the episode's start: cubes from ``[cube]``, the goal from ``[target]``."""
        cubes = draw_cubes(spec, rng)
        target = np.array([rng.uniform(*spec.target_x), rng.uniform(*spec.target_y)])
        return Layout(np.array(cubes, dtype=np.float64), target)

    def layout_points(self, spec: TaskSpec, layout: Layout) -> list[np.ndarray]:
        """Points that must lie in reach and ``min_separation`` apart (cubes and the goal)."""
        return [*(c[:2] for c in layout.cubes), layout.target]

    def acceptable(self, spec: TaskSpec, layout: Layout) -> bool:
        points = self.layout_points(spec, layout)
        return in_reach(spec, points) and all_separated(spec, points)

    def sample_layout(self, spec: TaskSpec, rng: np.random.Generator) -> Layout:
        """Draw until the layout rules hold (the first draw of pick_place always does)."""
        for _ in range(MAX_DRAWS):
            layout = self.draw(spec, rng)
            if self.acceptable(spec, layout):
                return layout
        raise ValueError(
            f"{spec.source or spec.name}: no layout satisfies the task's rules in {MAX_DRAWS} "
            f"draws (cube x {list(spec.cube_x)}, y {list(spec.cube_y)}; target x "
            f"{list(spec.target_x)}, y {list(spec.target_y)}; reach {spec.reach}; "
            f"min_separation {spec.min_separation}); widen the ranges or relax [layout]")

    # ------------------------------------------------------------------ scene
    def cube_names(self, spec: TaskSpec) -> list[str]:
        """Free-body cubes in ``environment_state`` order: the task's cubes, then any other."""
        return ["cube"] + [f"cube_{i}" for i in range(1, spec.n_cubes)]

    def cube_sizes(self, spec: TaskSpec, cube_size: float | None = None) -> list[float]:
        """Edge lengths in ``cube_names`` order; `cube_size` replaces the task cubes' size."""
        return [spec.cube_size if cube_size is None else cube_size] * spec.n_cubes

    def furnish(self, mjspec: mujoco.MjSpec, spec: TaskSpec) -> None:
        """Add this kind's objects to the scene (called before compiling; default: none)."""

    def env_state_size(self, spec: TaskSpec) -> int:
        """Length of ``environment_state``: 10, plus 7 per further free cube."""
        return ENV_STATE_BASE + 7 * (len(self.cube_names(spec)) - 1)

    # ------------------------------------------------------------------ episode
    def goal_height(self, spec: TaskSpec, cube_half: float) -> float:
        """Height of the ``target`` mocap body at reset (m)."""
        return 0.0

    def goal_pos(self, env: Any) -> np.ndarray:
        """Where the (first) cube should go, world frame (m)."""
        return env.data.mocap_pos[env.ids.target_mocap]

    def tracker(self) -> Tracker:
        """A fresh success tracker for one episode."""
        raise NotImplementedError(f"task kind {self.name!r} defines no tracker()")

    # ------------------------------------------------------------------ scripted expert
    def stages(self, spec: TaskSpec) -> int:
        """Cubes the expert moves in turn."""
        return spec.n_cubes

    def place(self, spec: TaskSpec, env_state: np.ndarray, cube: np.ndarray,
              stage: int) -> tuple[np.ndarray, float]:
        """Where cube `stage` goes: (x, y of its centre, height above its start in m)."""
        return env_state[7:9], 0.0

    def expert_plan(self, spec: TaskSpec, standard: Sequence[Segment],
                    ctx: PlanContext) -> list[Segment]:
        """The expert's segments; default: the standard pick-and-place ones."""
        return list(standard)


_REGISTRY: dict[str, TaskKind] = {}


def register_kind(cls: type[TaskKind]) -> type[TaskKind]:
    """Class decorator: make ``kind = cls.name`` usable in task files."""
    if not (isinstance(cls, type) and issubclass(cls, TaskKind)):
        raise TypeError(f"register_kind expects a TaskKind subclass, got {cls!r}")
    if not cls.name or not cls.name.isidentifier():
        raise ValueError(f"{cls.__name__}.name = {cls.name!r}; expected an identifier such "
                         "as 'shelf'")
    if "sim_unstable" not in cls.failure_modes:
        raise ValueError(f"{cls.__name__}.failure_modes lacks 'sim_unstable', which the env "
                         "reports when the simulation diverges; add it")
    _REGISTRY[cls.name] = cls()
    return cls


def registered_kinds() -> tuple[str, ...]:
    return tuple(sorted(_REGISTRY))


def get_kind(name: str) -> TaskKind:
    """The registered kind `name`, or a ValueError listing the registered ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"kind = {name!r} is not registered; expected one of "
                         f"{list(registered_kinds())}, or register your own with "
                         "@so101_sim.tasks.register_kind before loading the task") from None


def sample_layout(spec: TaskSpec, rng: np.random.Generator) -> Layout:
    """Draw the objects' start for `spec` from `rng` (its kind's rules)."""
    return get_kind(spec.kind).sample_layout(spec, rng)
