"""lift: pick the red cube up and hold it above the table.

**Description.** One red cube, no target pad; the arm grasps the cube and holds it up.

**Randomizations.** The cube's x, y and yaw from ``[cube]`` (``[layout] reach`` keeps it
where the arm reaches top-down). The goal (``environment_state`` and ``goal_pos``) is the
point ``success.lift_height`` above the cube's start.

**Success.** The cube held between both finger pads at least ``success.lift_height`` above its
resting height for ``success.hold_steps`` consecutive steps. Failure modes:
``never_grasped``, ``dropped``, ``too_low`` (lifted, never high enough), ``timeout`` (high,
not for long enough), ``sim_unstable``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from so101_sim.tasks.kind import PlanContext, Segment, TaskKind, register_kind
from so101_sim.tasks.layouts import PAN_AXIS_XY, Layout
from so101_sim.tasks.outcomes import Grasp
from so101_sim.tasks.props import remove_target_pad

LIFT_MARGIN = 0.01  # m: the expert holds the cube this far above the task's lift height
HOLD_STEPS = 90  # control steps the expert holds the cube up (the task ends at hold_steps)


class LiftOutcome:
    def __init__(self) -> None:
        self.high_steps = 0
        self.ever_high = False
        self.grasp = Grasp()

    def update(self, env: Any, action: np.ndarray) -> tuple[bool, float]:
        held, _ = self.grasp.update(env, 0, action)
        high = held and env.cube_pos(0)[2] >= env.cube_half(0) + env.task.lift_height
        self.ever_high |= high
        self.high_steps = self.high_steps + 1 if high else 0
        success = self.high_steps >= env.task.hold_steps
        return success, float(success)

    def failure_mode(self, env: Any) -> str:
        g = self.grasp
        if not g.ever_lifted:
            return "never_grasped"
        if g.dropped:
            return "dropped"
        if not self.ever_high:
            return "too_low"
        return "timeout"


@register_kind
class Lift(TaskKind):
    name = "lift"
    failure_modes: ClassVar[tuple[str, ...]] = ("never_grasped", "dropped", "too_low",
                                                "timeout", "sim_unstable")
    # A lift file has no [target] section and no place rules.
    spec_defaults: ClassVar[dict[str, Any]] = {
        "target_x": (0.0, 0.0), "target_y": (0.0, 0.0), "target_radius": 0.0,
        "settle_steps": 1, "max_speed": 0.02, "release_clearance": 0.0}

    def check(self, spec: Any, source: str) -> str | None:
        if spec.hold_steps > spec.max_steps:
            return (f"success.hold_steps = {spec.hold_steps} is too large; expected at most "
                    f"episode.max_steps = {spec.max_steps}")
        return None

    def draw(self, spec: Any, rng: np.random.Generator) -> Layout:
        layout = super().draw(spec, rng)
        layout.target = np.array(layout.cubes[0][:2])  # the lift point is above the cube
        return layout

    def layout_points(self, spec: Any, layout: Layout) -> list[np.ndarray]:
        return [c[:2] for c in layout.cubes]

    def furnish(self, mjspec: Any, spec: Any) -> None:
        remove_target_pad(mjspec)

    def goal_height(self, spec: Any, cube_half: float) -> float:
        return cube_half + spec.lift_height

    def tracker(self) -> LiftOutcome:
        return LiftOutcome()

    def expert_plan(self, spec: Any, standard: Sequence[Segment],
                    ctx: PlanContext) -> list[Segment]:
        """Approach, descend, close as usual; then lift and hold (no carry, no place)."""
        q_up = hold_pose(spec, ctx)
        return [*standard[:3], ("lift", 25, ctx.act(q_up, ctx.closed)),
                ("hold", HOLD_STEPS, ctx.act(q_up, ctx.closed))]


def hold_pose(spec: Any, ctx: PlanContext) -> np.ndarray:
    """Straight up from the grasp or, where the arm does not reach that high, drawn in
    towards the base (far out) or out (close in) until it does: the height is what counts."""
    up = max(ctx.carry_height, spec.lift_height + LIFT_MARGIN)
    inward = np.asarray(PAN_AXIS_XY) - ctx.grasp[:2]
    inward /= max(float(np.linalg.norm(inward)), 1e-9)
    for pull in (0.0, 0.02, -0.02, 0.04, -0.04, 0.06, 0.08):
        q_up, err = ctx.ik.solve(ctx.grasp + np.r_[pull * inward, up], ctx.yaw, ctx.q_grasp)
        if err < 2e-3:
            break
    return q_up
