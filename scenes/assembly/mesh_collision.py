"""Convex parts for a mesh object's collision shape (coacd), computed once per mesh.

MuJoCo collides a mesh geom as its convex hull, so a mug or a bowl would be a
solid lump. A task object made from a mesh therefore collides as the convex
parts of an approximate convex decomposition (CoACD). The decomposition takes
seconds to minutes, so its result is cached under a key made of the mesh
file's bytes and the parameters: first next to the mesh (`NAME.coacd-KEY.npz`,
shipped with the library's meshes), then in the user cache
(`$TELEOP_CACHE/coacd`, else `~/.cache/mujoco-teleop/coacd`). Parts are in the
mesh file's own coordinates (unscaled); a uniform or per-axis scale keeps a
convex part convex, so the loader scales them as it scales the mesh.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from scenes.errors import TeleopError

CACHE_ENV = "TELEOP_CACHE"


class MeshError(TeleopError):
    """A mesh file that cannot be read or decomposed; `reason` is the message without the file's name."""

    def __init__(self, message: str, reason: str | None = None) -> None:
        super().__init__(message)
        self.reason = reason if reason is not None else message


def _mesh_error(path: Path, reason: str) -> MeshError:
    """A MeshError naming `path`, whose `reason` lets a caller name the file its own way (as its user wrote it)."""
    return MeshError(f"mesh {path}: {reason}", reason)


@dataclass(frozen=True)
class CoacdParams:
    """CoACD settings, tuned for speed on small household objects (seconds, not minutes).

    threshold: concavity allowed per part (fraction of the bounding-box diagonal);
    max_convex_hull: most parts kept (merged down to this); preprocess_resolution:
    voxels along the longest side when making the input manifold; resolution:
    samples for the concavity metric; mcts_*: the cutting-plane search.
    """

    threshold: float = 0.08
    max_convex_hull: int = 16
    preprocess_mode: str = "auto"
    preprocess_resolution: int = 30
    resolution: int = 1000
    mcts_nodes: int = 12
    mcts_iterations: int = 60
    mcts_max_depth: int = 2
    seed: int = 0


Parts = list[tuple[np.ndarray, np.ndarray]]  # (vertices (n, 3) float64 in m, faces (m, 3) int32) per convex part


def load_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of an OBJ or STL file, triangulated; a MeshError names the file on failure."""
    import trimesh

    path = Path(path)
    if path.suffix.lower() not in (".obj", ".stl"):
        raise _mesh_error(path, "only .obj and .stl are supported")
    if not path.is_file():
        raise _mesh_error(path, "no such file")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds on a malformed file
        raise _mesh_error(path, f"cannot be read ({type(exc).__name__}: {exc})".splitlines()[0]) from None
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32)
    if len(faces) == 0 or not np.all(np.isfinite(vertices)) or np.ptp(vertices, axis=0).min() <= 0:
        raise _mesh_error(path, "has no triangles with volume")
    return vertices, faces


def cache_key(path: Path, params: CoacdParams = CoacdParams()) -> str:
    """sha256 of the mesh file's bytes and the parameters (hex, 16 characters)."""
    digest = hashlib.sha256(Path(path).read_bytes())
    digest.update(json.dumps(asdict(params), sort_keys=True).encode())
    return digest.hexdigest()[:16]


def user_cache_dir() -> Path:
    root = os.environ.get(CACHE_ENV)
    return (Path(root) if root else Path.home() / ".cache" / "mujoco-teleop") / "coacd"


def shipped_path(path: Path, key: str) -> Path:
    """Where parts shipped with a mesh live: beside it, named by the mesh and the key."""
    path = Path(path)
    return path.with_name(f"{path.stem}.coacd-{key}.npz")


def decompose(vertices: np.ndarray, faces: np.ndarray, params: CoacdParams = CoacdParams()) -> Parts:
    """Run CoACD on a triangle mesh (silently) and return its convex parts."""
    import coacd

    coacd.set_log_level("error")
    fields = asdict(params)
    result = coacd.run_coacd(coacd.Mesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int32)), **fields)
    parts = [(np.asarray(v, np.float64), np.asarray(f, np.int32)) for v, f in result]
    if not parts:
        raise MeshError("coacd returned no convex parts")
    return parts


def _save(parts: Parts, target: Path) -> None:
    arrays = {}
    for i, (v, f) in enumerate(parts):
        arrays[f"v{i}"], arrays[f"f{i}"] = v, f
    buffer = io.BytesIO()
    np.savez_compressed(buffer, count=np.array(len(parts)), **arrays)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=target.parent, delete=False, suffix=".tmp") as tmp:
        tmp.write(buffer.getvalue())
    os.replace(tmp.name, target)  # atomic: parallel workers never read half a file


def _load(target: Path) -> Parts | None:
    try:
        with np.load(target) as data:
            return [(data[f"v{i}"], data[f"f{i}"]) for i in range(int(data["count"]))]
    except (OSError, KeyError, ValueError):
        return None  # a damaged cache entry is recomputed


def cached_parts(path: Path, params: CoacdParams = CoacdParams()) -> Parts | None:
    """The parts if already computed (shipped beside the mesh or in the user cache), else None."""
    key = cache_key(path, params)
    for target in (shipped_path(path, key), user_cache_dir() / f"{key}.npz"):
        if target.is_file():
            parts = _load(target)
            if parts is not None:
                return parts
    return None


def convex_parts(path: Path, params: CoacdParams = CoacdParams()) -> Parts:
    """Convex parts of the mesh at `path`, in its own units: from a cache, else computed and cached."""
    path = Path(path)
    vertices, faces = load_mesh(path)  # validates the file even on a cache hit
    parts = cached_parts(path, params)
    if parts is None:
        parts = decompose(vertices, faces, params)
        try:
            _save(parts, user_cache_dir() / f"{cache_key(path, params)}.npz")
        except OSError:
            pass  # a read-only home still gets its parts, just not cached
    return parts


def ship_parts(path: Path, params: CoacdParams = CoacdParams()) -> Path:
    """Compute (or reuse) the parts of a library mesh and write them beside it; returns that file."""
    path = Path(path)
    target = shipped_path(path, cache_key(path, params))
    for stale in path.parent.glob(f"{path.stem}.coacd-*.npz"):
        if stale != target:
            stale.unlink()
    if not target.is_file():
        _save(convex_parts(path, params), target)
    return target


def parts_obj_bytes(parts: Parts, scale: np.ndarray | float = 1.0) -> list[bytes]:
    """Each part as OBJ bytes, scaled (per axis or uniformly): assets a model can embed."""
    out = []
    for v, f in parts:
        v = np.asarray(v) * np.asarray(scale, dtype=np.float64)
        lines = [f"v {x:.7g} {y:.7g} {z:.7g}" for x, y, z in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
        out.append(("\n".join(lines) + "\n").encode())
    return out
