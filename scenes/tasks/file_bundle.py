"""A task file's source packed into an episode and unpacked again: the TOML text and every file it names.

Files travel base64-encoded under their paths as the task file wrote them, meshes with
their convex parts (`.npz`), so replay, re-judging and generation need nothing else.
Unpacked bundles go once under the user cache ($TELEOP_CACHE or ~/.cache/mujoco-teleop).
"""

from __future__ import annotations

import base64
import hashlib
import io
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from scenes.errors import first_line
from scenes.tasks.file_values import TaskFileError


def make_bundle(name: str, path: Path, toml_text: str, files: Mapping[str, Path]) -> dict[str, Any]:
    """The task's source as JSON: the TOML text and every file it names (base64), convex parts included."""
    from scenes.assembly.mesh_collision import cache_key, cached_parts, shipped_path

    out: dict[str, str] = {}
    for rel, file in files.items():
        out[rel] = base64.b64encode(file.read_bytes()).decode()
        if file.suffix.lower() in (".obj", ".stl"):
            key = cache_key(file)
            shipped = shipped_path(file, key)
            parts_rel = str(Path(rel).with_name(shipped.name).as_posix())
            if shipped.is_file():
                out[parts_rel] = base64.b64encode(shipped.read_bytes()).decode()
            else:
                parts = cached_parts(file)
                if parts is not None:
                    arrays = {}
                    for i, (v, f) in enumerate(parts):
                        arrays[f"v{i}"], arrays[f"f{i}"] = v, f
                    buffer = io.BytesIO()
                    np.savez_compressed(buffer, count=np.array(len(parts)), **arrays)
                    out[parts_rel] = base64.b64encode(buffer.getvalue()).decode()
    return {"name": name, "file": path.name, "toml": toml_text, "files": out}


def bundle_dir() -> Path:
    """Where unpacked bundles go: one folder per bundle's content hash."""
    root = os.environ.get("TELEOP_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "mujoco-teleop") / "tasks"


def unpack_bundle(bundle: Mapping[str, Any]) -> Path:
    """Write what an episode stored (`make_bundle`) under the user cache, once; returns the TOML file's path."""
    try:
        text = str(bundle["toml"])
        files = {str(k): base64.b64decode(v) for k, v in dict(bundle.get("files") or {}).items()}
        file_name = Path(str(bundle.get("file") or "task.toml")).name
    except (KeyError, TypeError, ValueError) as exc:
        raise TaskFileError(f"the episode's task_file is damaged: {first_line(exc)}") from None
    digest = hashlib.sha256(text.encode())
    for rel in sorted(files):
        digest.update(rel.encode() + b"\0" + files[rel])
    depth = max([Path(rel).parts.count("..") for rel in files] + [0])
    root = bundle_dir() / digest.hexdigest()[:16]
    home = root.joinpath(*(["t"] * depth))
    for rel, data in files.items():
        target = Path(os.path.normpath(home / rel))
        if root not in target.parents:
            raise TaskFileError(f"the episode's task_file names a file outside its folder: {rel!r}")
        if not target.is_file() or target.read_bytes() != data:
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_suffix(target.suffix + ".tmp")
            tmp.write_bytes(data)
            os.replace(tmp, target)
    toml_path = home / file_name
    home.mkdir(parents=True, exist_ok=True)
    if not toml_path.is_file() or toml_path.read_text() != text:
        toml_path.write_text(text)
    return toml_path
