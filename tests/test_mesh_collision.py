"""Mesh objects collide as convex parts from a real coacd run, computed once and cached by hash."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from scenes.assets.make_meshes import MESHES, MJCF
from scenes.assembly.mesh_collision import (
    CoacdParams, MeshError, cache_key, cached_parts, convex_parts, parts_obj_bytes, shipped_path, user_cache_dir,
)

MESH_DIR = Path(__file__).resolve().parents[1] / "scenes" / "assets" / "meshes"


def _inside(parts, point) -> bool:
    """Whether `point` lies inside any part's convex hull (all outward face planes on its far side)."""
    for v, f in parts:
        hull = trimesh.Trimesh(v, f).convex_hull
        if np.all(np.einsum("ij,ij->i", hull.face_normals, np.asarray(point) - hull.triangles[:, 0]) < 0):
            return True
    return False


def _l_shape(path: Path) -> Path:
    """A small concave L: two 4 x 1 x 1 cm boxes meeting at a corner, written as OBJ."""
    a = trimesh.creation.box([0.04, 0.01, 0.01], trimesh.transformations.translation_matrix([0.02, 0.005, 0.005]))
    b = trimesh.creation.box([0.01, 0.04, 0.01], trimesh.transformations.translation_matrix([0.005, 0.02, 0.005]))
    trimesh.util.concatenate([a, b]).export(path)
    return path


def test_l_shape_decomposes_and_the_second_call_hits_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TELEOP_CACHE", str(tmp_path / "cache"))
    mesh = _l_shape(tmp_path / "ell.obj")
    assert cached_parts(mesh) is None
    parts = convex_parts(mesh)
    assert len(parts) >= 2  # an L is not convex: one hull would fill its inner corner
    assert not _inside(parts, [0.03, 0.03, 0.005])  # inside the L's bounding box, outside the L
    assert _inside(parts, [0.035, 0.005, 0.005])  # the arm of the L is solid
    entry = user_cache_dir() / f"{cache_key(mesh)}.npz"
    assert entry.is_file() and entry.parent == tmp_path / "cache" / "coacd"
    again = cached_parts(mesh)
    assert again is not None and len(again) == len(parts)
    assert all(np.array_equal(v1, v2) and np.array_equal(f1, f2) for (v1, f1), (v2, f2) in zip(parts, again))
    # Other parameters or other bytes are another key: no stale parts.
    assert cache_key(mesh, CoacdParams(threshold=0.2)) != cache_key(mesh)
    mesh.write_text(mesh.read_text() + "\n")
    assert cached_parts(mesh) is None


def test_library_meshes_ship_their_parts(tmp_path, monkeypatch):
    monkeypatch.setenv("TELEOP_CACHE", str(tmp_path / "empty"))  # only the shipped parts can answer
    assert len(MESHES) >= 6
    for name in MESHES:
        path = MESH_DIR / f"{name}.obj"
        assert shipped_path(path, cache_key(path)).is_file(), f"{name}: run scenes/assets/make_meshes.py --collision"
        parts = cached_parts(path)
        assert parts, name
        lo, hi = trimesh.load(path).bounds
        for v, _ in parts:  # parts stay within the mesh's box (a little slack for hull rounding)
            assert np.all(v.min(axis=0) >= lo - 0.003) and np.all(v.max(axis=0) <= hi + 0.003), name
    assert not (tmp_path / "empty").exists()
    for name in MJCF:
        assert (MESH_DIR / f"{name}.xml").is_file()


def test_vessels_stay_hollow():
    """A mug's parts leave its inside free, so something can be put in it."""
    for name, probe in (("mug", [0, 0, 0.05]), ("bowl", [0, 0, 0.03]), ("cup", [0, 0, 0.05]), ("basket", [0, 0, 0.03])):
        parts = cached_parts(MESH_DIR / f"{name}.obj")
        assert not _inside(parts, probe), name
        assert _inside(parts, [0.0, 0.0, 0.003]), name  # the bottom is solid


def test_parts_become_scaled_obj_assets():
    parts = cached_parts(MESH_DIR / "can.obj")
    blobs = parts_obj_bytes(parts, scale=[2.0, 2.0, 1.0])
    mesh = trimesh.load(trimesh.util.wrap_as_stream(blobs[0]), file_type="obj")
    assert mesh.bounds[1][0] == pytest.approx(2 * parts[0][0][:, 0].max(), rel=1e-5)
    assert mesh.bounds[1][2] == pytest.approx(parts[0][0][:, 2].max(), rel=1e-5)


def test_bad_meshes_are_one_line(tmp_path):
    with pytest.raises(MeshError, match="no such file"):
        convex_parts(tmp_path / "missing.obj")
    with pytest.raises(MeshError, match="only .obj and .stl"):
        convex_parts(tmp_path / "thing.ply")
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="no triangles with volume") as info:
        convex_parts(flat)
    assert "\n" not in str(info.value)
