"""An object's resolved shape at a layout: footprint radius and height (m), its mesh and convex parts, its mjcf.

Needed before placement (objects keep their footprints apart) and for building;
it depends on the layout's units only, never on the seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from scenes.errors import first_line
from scenes.tasks.file_schema import ObjectDef
from scenes.tasks.file_values import TaskFileError, length, lengths, numbers
from scenes.tasks.geometry import Units


@dataclass
class Geometry:
    """An object's resolved shape: footprint radius (m), extent below/above its origin (m), and parts."""

    radius: float
    below: float
    above: float
    mesh: tuple[np.ndarray, np.ndarray] | None = None
    parts: list | None = None
    mjcf: mujoco.MjSpec | None = None
    _obj_files: tuple[bytes, list[bytes]] | None = field(default=None, repr=False, compare=False)

    def obj_files(self) -> tuple[bytes, list[bytes]]:
        """A mesh object's visual mesh and convex parts as OBJ bytes (the model's assets), written once: a
        task's geometries serve every reset, and writing them is 12 ms a part."""
        if self._obj_files is None:
            from scenes.assembly.mesh_collision import parts_obj_bytes

            if self.mesh is None:
                raise ValueError("not a mesh object: it has no OBJ files")
            self._obj_files = (parts_obj_bytes([self.mesh])[0], parts_obj_bytes(self.parts or []))
        return self._obj_files


def euler_matrix(euler: Any) -> np.ndarray:
    """The rotation matrix of xyz Euler angles (rad)."""
    quat = np.zeros(4)
    mujoco.mju_euler2Quat(quat, np.asarray(euler, float), "xyz")
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, quat)
    return mat.reshape(3, 3)


def object_geometry(obj: ObjectDef, u: Units) -> Geometry:
    """`obj`'s shape in metres at units `u` (a mesh is loaded and split into convex parts, cached)."""
    raw, w = obj.raw, obj.where
    if obj.shape == "box":
        hx, hy, hz = lengths(raw["box"], 3, u, f"{w}: box")
        geo = Geometry(math.hypot(hx, hy), hz, hz)
    elif obj.shape in ("cylinder", "capsule"):
        r, h = lengths(raw[obj.shape], 2, u, f"{w}: {obj.shape}")
        geo = Geometry(r, h + (r if obj.shape == "capsule" else 0.0), h + (r if obj.shape == "capsule" else 0.0))
    elif obj.shape == "sphere":
        (r,) = lengths(raw["sphere"], 1, u, f"{w}: sphere")
        geo = Geometry(r, r, r)
    elif obj.shape == "bin":
        hx, hy, height = lengths(raw["bin"], 3, u, f"{w}: bin")
        wall = length(raw.get("wall", 0.004), u, f"{w}: wall") if "wall" in raw else 0.004
        geo = Geometry(math.hypot(hx + 2 * wall, hy + 2 * wall), 0.0, height)
    elif obj.shape == "mesh":
        from scenes.assembly.mesh_collision import MeshError, convex_parts, load_mesh

        scale = np.asarray(numbers(raw.get("scale", 1.0), (1, 3), f"{w}: scale"), float) * u.scale
        try:
            vertices, faces = load_mesh(obj.file)  # type: ignore[arg-type]
            parts = convex_parts(obj.file)  # type: ignore[arg-type]
        except MeshError as exc:
            raise TaskFileError(f"{w}: mesh: {raw['mesh']}: {exc.reason}") from None  # the file as the task file names it
        v = vertices * scale
        rot = euler_matrix(raw.get("euler", [0.0, 0.0, 0.0]))
        vr = v @ rot.T
        geo = Geometry(float(np.max(np.linalg.norm(vr[:, :2], axis=1))), float(-vr[:, 2].min()), float(vr[:, 2].max()),
                       mesh=(v, faces), parts=[(pv * scale, pf) for pv, pf in parts])
    else:
        child = mjcf_spec(obj, u)
        try:
            model = child.copy().compile()
        except Exception as exc:
            raise TaskFileError(f"{w}: mjcf: does not compile: {first_line(exc)}") from None
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        radius, hi = 0.0, 0.0
        for g in range(model.ngeom):
            p, rb = data.geom_xpos[g], float(model.geom_rbound[g])
            radius = max(radius, float(np.linalg.norm(p[:2])) + rb)
            hi = max(hi, float(p[2]) + rb)
        geo = Geometry(radius, 0.0, hi, mjcf=child)  # an mjcf thing's origin stands on the table
    return geo


def mjcf_spec(obj: ObjectDef, u: Units) -> mujoco.MjSpec:
    """An mjcf object's spec, its lengths scaled by the file's scale (no files of its own allowed)."""
    w = f"{obj.where}: mjcf"
    try:
        child = mujoco.MjSpec.from_file(str(obj.file))
    except Exception as exc:
        raise TaskFileError(f"{w}: does not load: {first_line(exc)}") from None
    if any(m.file for m in child.meshes) or any(t.file for t in child.textures):
        raise TaskFileError(f"{w}: an mjcf object may not reference files (use a mesh object for meshes)")
    f = u.scale
    if f != 1.0:
        for b in child.bodies[1:]:
            b.pos = np.asarray(b.pos) * f
        for g in child.geoms:
            g.size = np.asarray(g.size) * f
            g.pos = np.asarray(g.pos) * f
            if not np.isnan(g.fromto[0]):
                g.fromto = np.asarray(g.fromto) * f
        for s in child.sites:
            s.size = np.asarray(s.size) * f
            s.pos = np.asarray(s.pos) * f
        for j in child.joints:
            j.pos = np.asarray(j.pos) * f
            if int(j.type) == int(mujoco.mjtJoint.mjJNT_SLIDE):
                j.range = np.asarray(j.range) * f
    return child
