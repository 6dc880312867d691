"""Domain randomization: applies one draw of a task's ``[randomize]`` ranges to an env.

The env owns a private copy of the model; ``DomainRandomizer`` remembers its nominal values
and, at every reset, sets each randomized factor from the nominal value and a fresh draw, so
nothing accumulates across episodes. Draws come from the generator the env passes in (a
stream seeded by the reset seed, separate from the layout stream), always in the same order,
so the same seed gives the same scene, pixels included.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from so101_sim.sim.glcheck import mujoco
from so101_sim.sim.scene import TABLE_TEXTURE_SIZE, cube_names, is_descendant
from so101_sim.tasks import TaskSpec, get_kind
from so101_sim.tasks.layouts import PAN_AXIS_XY
from so101_sim.utils.units import MOTOR_NAMES

WORKSPACE_CENTRE = np.array([0.17, 0.0, 0.04])  # the fixed cameras aim here (scene XML)
LIGHT_DISTANCE = 1.25  # m from the workspace centre to the key light (its distance in the XML)
JITTERED_CAMERAS = ("front", "side")  # the wrist camera is bolted to the gripper
DISTRACTOR_CLEARANCE = 0.09  # m from any cube or the goal (they must not hide them)
HIDDEN = (0.0, 0.0, -0.5)  # under the table: where unused distractors wait


class DomainRandomizer:
    """Applies draws of ``task.randomize`` to `model` (the env's own copy)."""

    def __init__(self, model: mujoco.MjModel, task: TaskSpec) -> None:
        assert task.randomize is not None
        self.model, self.task, self.r = model, task, task.randomize
        m = model
        self.light = m.light("key").id
        self.table = m.geom("table").id
        self.cube_geoms = [m.geom(n).id for n in cube_names(task)[:task.n_cubes]]
        self.cube_bodies = [m.body(n).id for n in cube_names(task)[:task.n_cubes]]
        self.nominal_cube = (m.geom_size[self.cube_geoms[0]].copy(),
                             float(m.body_mass[self.cube_bodies[0]]),
                             m.geom_friction[self.cube_geoms[0]].copy())
        self.yellow = m.material("yellow").id if _has(m, mujoco.mjtObj.mjOBJ_MATERIAL,
                                                      "yellow") else -1
        base = m.body("base").id
        nominal_yellow = np.array([1, 0.82, 0.12, 1], dtype=np.float32)
        self.robot_geoms = [g for g in range(m.ngeom)
                            if is_descendant(m, m.geom_bodyid[g], base)
                            and np.allclose(m.geom_rgba[g], nominal_yellow)]
        self.cams = [m.camera(c).id for c in JITTERED_CAMERAS]
        self.nominal_cams = (m.cam_pos[self.cams].copy(), m.cam_quat[self.cams].copy(),
                             m.cam_fovy[self.cams].copy())
        self.actuators = [m.actuator(n).id for n in MOTOR_NAMES]
        self.dofs = [m.jnt_dofadr[m.joint(n).id] for n in MOTOR_NAMES]
        self.nominal_servo = (m.actuator_gainprm[self.actuators, 0].copy(),
                              m.actuator_biasprm[self.actuators, 1:3].copy(),
                              m.dof_damping[self.dofs].copy())
        self.table_tex = (m.texture("table_tex").id
                          if _has(m, mujoco.mjtObj.mjOBJ_TEXTURE, "table_tex") else -1)
        n = self.r.distractors[1] if self.r.distractors is not None else 0
        self.distractors = [(int(m.body_mocapid[m.body(f"distractor_{i}").id]),
                             m.geom(f"distractor_{i}").id) for i in range(n)]
        self._texture_version = 0  # counts the table textures drawn

    # ------------------------------------------------------------------ one draw per reset
    def apply(self, rng: np.random.Generator, data: mujoco.MjData,
              cubes: np.ndarray, goal: Sequence[float]) -> list[float]:
        """Draw every randomized factor and set it; returns the cubes' edge lengths
        (``TaskKind.cube_sizes``: the task's cubes, then any other at its nominal size).
        `cubes` are the layout's (x, y, yaw) rows, `goal` the target's x, y (distractors
        keep clear of both)."""
        self._lights(rng)
        self._colours(rng)
        self._cameras(rng)
        size = self._cube_physics(rng)
        self._servos(rng)
        mujoco.mj_setConst(self.model, data)  # masses and inertias feed the solver's constants
        self._place_distractors(rng, data, cubes, goal)
        return get_kind(self.task.kind).cube_sizes(self.task, size)

    def upload(self, renderer: Any) -> None:
        """Give `renderer` this episode's table texture (a no-op once it has it)."""
        if self.table_tex >= 0:
            renderer.upload_texture(self.table_tex, self._texture_version, nearest=True)

    def _lights(self, rng: np.random.Generator) -> None:
        m, r = self.model, self.r
        if r.light_azimuth is not None or r.light_elevation is not None:
            # Unrandomized half: the XML's own direction (-0.2, 0.25, -1) points away from
            # azimuth -51.3, elevation 72.6 degrees.
            az = np.deg2rad(rng.uniform(*(r.light_azimuth or (-51.3, -51.3))))
            el = np.deg2rad(rng.uniform(*(r.light_elevation or (72.6, 72.6))))
            towards_light = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                      np.sin(el)])
            m.light_pos[self.light] = WORKSPACE_CENTRE + LIGHT_DISTANCE * towards_light
            m.light_dir[self.light] = -towards_light
        if r.light_intensity is not None:
            m.light_diffuse[self.light] = rng.uniform(*r.light_intensity)
        if r.ambient is not None:
            m.vis.headlight.ambient = [rng.uniform(*r.ambient)] * 3

    def _colours(self, rng: np.random.Generator) -> None:
        m, r = self.model, self.r
        if r.table_color is not None:  # an explicit geom rgba also tints the texture
            m.geom_rgba[self.table] = np.r_[rng.uniform(*r.table_color), 1.0]
        if r.table_texture is not None and self.table_tex >= 0:
            contrast = rng.uniform(*r.table_texture)
            pattern = _table_pattern(rng, TABLE_TEXTURE_SIZE)
            texels = np.clip(255 * (1 - contrast * pattern), 0, 255).astype(np.uint8)
            adr, n = m.tex_adr[self.table_tex], TABLE_TEXTURE_SIZE * TABLE_TEXTURE_SIZE * 3
            m.tex_data[adr:adr + n] = np.repeat(texels.ravel(), 3)
            self._texture_version += 1
        if r.cube_color is not None:
            for g in self.cube_geoms:
                m.geom_rgba[g] = np.r_[rng.uniform(*r.cube_color), 1.0]
        if r.robot_color is not None:
            rgba = np.r_[rng.uniform(*r.robot_color), 1.0]
            if self.yellow >= 0:
                m.mat_rgba[self.yellow] = rgba
            m.geom_rgba[self.robot_geoms] = rgba

    def _cameras(self, rng: np.random.Generator) -> None:
        m, r = self.model, self.r
        pos0, quat0, fovy0 = self.nominal_cams
        for i, cam in enumerate(self.cams):
            if r.camera_position is not None:
                m.cam_pos[cam] = pos0[i] + rng.uniform(*r.camera_position, size=3)
            if r.camera_rotation is not None:
                axis = rng.normal(size=3)
                angle = np.deg2rad(rng.uniform(*r.camera_rotation))
                turn = np.zeros(4)
                mujoco.mju_axisAngle2Quat(turn, axis / np.linalg.norm(axis), angle)
                quat = np.zeros(4)
                mujoco.mju_mulQuat(quat, turn, quat0[i])
                m.cam_quat[cam] = quat
            if r.camera_fovy is not None:
                m.cam_fovy[cam] = fovy0[i] + rng.uniform(*r.camera_fovy)

    def _cube_physics(self, rng: np.random.Generator) -> float:
        m, r = self.model, self.r
        size0, mass0, friction0 = self.nominal_cube
        size = rng.uniform(*r.cube_size) if r.cube_size is not None else 2 * float(size0[0])
        mass = rng.uniform(*r.cube_mass) if r.cube_mass is not None else mass0
        friction = rng.uniform(*r.cube_friction) if r.cube_friction is not None else friction0[0]
        h = size / 2
        for g, b in zip(self.cube_geoms, self.cube_bodies, strict=True):
            m.geom_size[g] = [h, h, h]
            m.geom_rbound[g] = h * np.sqrt(3)
            m.geom_aabb[g] = [0, 0, 0, h, h, h]
            m.geom_friction[g, 0] = friction
            m.body_mass[b] = mass
            m.body_inertia[b] = mass * size * size / 6  # solid cube
        return size

    def _servos(self, rng: np.random.Generator) -> None:
        m, r = self.model, self.r
        kp0, bias0, damping0 = self.nominal_servo
        gain = rng.uniform(*r.servo_gain) if r.servo_gain is not None else 1.0
        damp = rng.uniform(*r.servo_damping) if r.servo_damping is not None else 1.0
        m.actuator_gainprm[self.actuators, 0] = kp0 * gain
        m.actuator_biasprm[self.actuators, 1] = bias0[:, 0] * gain  # -kp
        m.actuator_biasprm[self.actuators, 2] = bias0[:, 1] * damp  # -kv
        m.dof_damping[self.dofs] = damping0 * damp

    def _place_distractors(self, rng: np.random.Generator, data: mujoco.MjData,
                           cubes: np.ndarray, goal: Sequence[float]) -> None:
        if not self.distractors:
            return
        m, (lo, hi) = self.model, self.r.distractors
        count = int(rng.integers(lo, hi + 1))
        keep_clear = [np.asarray(c[:2]) for c in cubes] + [np.asarray(goal[:2])]
        for i, (mocap, geom) in enumerate(self.distractors):
            if i >= count:  # out of the way, and alpha 0: MuJoCo does not draw it at all
                data.mocap_pos[mocap] = HIDDEN
                m.geom_rgba[geom, 3] = 0.0
                continue
            half = rng.uniform(0.008, 0.025, size=3)  # flat slabs to tall blocks
            yaw = rng.uniform(0, np.pi)
            rgba = np.r_[rng.uniform(0.1, 0.95, size=3), 1.0]
            for _ in range(100):  # on the table, in view, clear of the task's objects
                xy = np.array([rng.uniform(0.08, 0.34), rng.uniform(-0.26, 0.26)])
                if (np.hypot(*(xy - PAN_AXIS_XY)) > 0.1
                        and all(np.linalg.norm(xy - p) > DISTRACTOR_CLEARANCE
                                for p in keep_clear)):
                    break
            m.geom_size[geom] = half
            m.geom_rbound[geom] = float(np.linalg.norm(half))
            m.geom_aabb[geom] = [0, 0, 0, *half]
            m.geom_rgba[geom] = rgba
            data.mocap_pos[mocap] = [xy[0], xy[1], half[2]]  # standing on the table
            data.mocap_quat[mocap] = [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
            keep_clear.append(xy)


def _has(m: mujoco.MjModel, kind: mujoco.mjtObj, name: str) -> bool:
    return mujoco.mj_name2id(m, kind, name) >= 0


def _table_pattern(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, n) values in 0..1: wood-like grain, a checker or soft blotches, drawn from `rng`.
    Integer frequencies make every pattern periodic, so the repeated texture has no seams."""
    y, x = np.mgrid[0:n, 0:n] / n
    kind = int(rng.integers(3))
    phase = rng.uniform(0, 2 * np.pi, size=3)
    if kind == 0:  # grain: stripes bent by a slow wave
        f = int(rng.integers(4, 12))
        v = 0.5 + 0.5 * np.sin(2 * np.pi * f * (x + 0.04 * np.sin(2 * np.pi * 2 * y + phase[0]))
                               + phase[1])
    elif kind == 1:  # checker (tiles)
        k = int(rng.integers(1, 5))
        v = ((np.floor(x * 2 * k) + np.floor(y * 2 * k)) % 2).astype(float)
    else:  # blotches: a few summed waves
        v = sum(np.sin(2 * np.pi * (int(rng.integers(1, 4)) * x + int(rng.integers(1, 4)) * y)
                       + p) for p in phase)
        v = (v - v.min()) / max(float(np.ptp(v)), 1e-9)
    return v


__all__ = ["DomainRandomizer"]
