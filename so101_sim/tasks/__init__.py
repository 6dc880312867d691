"""Tasks: what an episode asks for. Task files (specs), layouts, success rules, task kinds.

The first stage of the pipeline, below the simulation: nothing here renders or steps
physics. ``load_task`` parses a TOML file of ``envs/`` (or any path) into a ``TaskSpec``;
its ``kind`` names a registered ``TaskKind``, which owns the kind's layout rules, the
objects it adds to the scene, its goal, success tracker and failure modes, and how the
scripted expert places. The suite's kinds are one file each (``pick_place``, ``lift``,
``stack``, ``tidy``); ``register_kind`` adds one from your own code.
"""

# The suite's kinds register themselves on import.
from so101_sim.tasks import lift, pick_place, stack, tidy  # noqa: F401
from so101_sim.tasks.kind import (
    PlanContext,
    TaskKind,
    Tracker,
    get_kind,
    register_kind,
    registered_kinds,
    sample_layout,
)
from so101_sim.tasks.layouts import PAN_AXIS_XY, Layout
from so101_sim.tasks.spec import (
    ALL_CAMERAS,
    DEFAULT_CAMERAS,
    DEFAULT_TASK,
    TaskSpec,
    TaskSpecError,
    available_tasks,
    load_task,
    loads_here,
    parse_task,
    resolve_task_path,
    task_ref,
)

__all__ = ["ALL_CAMERAS", "DEFAULT_CAMERAS", "DEFAULT_TASK", "PAN_AXIS_XY", "Layout",
           "PlanContext", "TaskKind", "TaskSpec", "TaskSpecError", "Tracker", "available_tasks",
           "failure_modes", "get_kind", "load_task", "loads_here", "parse_task", "register_kind",
           "registered_kinds", "resolve_task_path", "sample_layout", "task_ref"]


def failure_modes(kind: str) -> tuple[str, ...]:
    """Every failure mode a task of `kind` can end with (``info["failure_mode"]``)."""
    return get_kind(kind).failure_modes
