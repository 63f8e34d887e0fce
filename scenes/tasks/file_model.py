"""A task file's bodies, regions and cameras added to an arena spec, at the places placement drew.

Positions are world (m): the workspace centre plus the placed offset, on the table top.
A mesh object is seen through its mesh and collides through its convex parts; an mjcf
object is attached under its own name (`aliases` maps the object to its root body).
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from scenes.assembly.arena import TABLE_TOP, Layout, look_at_xyaxes, yaw_quat
from scenes.tasks.file_geometry import Geometry, mjcf_spec
from scenes.tasks.file_schema import ObjectDef
from scenes.tasks.file_values import TaskFileError, length, length_range, lengths
from scenes.tasks.geometry import OBJECTS_TEXT, UNITS_NUMERIC, Units
from scenes.tasks.placement import Placed

DEFAULT_FRICTION = (1.2, 0.01, 0.0005)
GREY = (0.55, 0.57, 0.6, 1.0)


def body_quat(euler: Any, yaw: float) -> list[float] | None:
    """Body quaternion: the fixed `euler` (xyz, rad) then the sampled yaw about world z; None for identity."""
    if euler is None and yaw == 0.0:
        return None
    q = np.array([1.0, 0.0, 0.0, 0.0])
    if euler is not None:
        mujoco.mju_euler2Quat(q, np.asarray(euler, float), "xyz")
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(yaw_quat(yaw)), q)
    return [float(v) for v in out]


def add_objects(spec: mujoco.MjSpec, objects: list[ObjectDef], placed: dict[str, Placed], geos: dict[str, Geometry],
                layout: Layout, u: Units, aliases: dict[str, str]) -> dict[str, bytes]:
    """Every object at its placed pose; returns the mesh assets they use and fills `aliases`."""
    assets: dict[str, bytes] = {}
    cx, cy = layout.center
    for obj in objects:
        p, geo = placed[obj.name], geos[obj.name]
        pos = [cx + float(p.xy[0]), cy + float(p.xy[1]), TABLE_TOP + p.z]
        add_object(spec, obj, geo, pos, body_quat(obj.raw.get("euler"), p.yaw), u, assets, aliases)
    return assets


def add_regions(spec: mujoco.MjSpec, regions: dict[str, dict], layout: Layout, u: Units) -> None:
    """Each region as a flat box site on the table (seen only when it has an rgba)."""
    cx, cy = layout.center
    for name, reg in regions.items():
        (xl, xh), (yl, yh) = length_range(reg["x"], u, name), length_range(reg["y"], u, name)
        center = [cx + (xl + xh) / 2, cy + (yl + yh) / 2, TABLE_TOP + 0.0005]
        half = [max((xh - xl) / 2, 0.0005), max((yh - yl) / 2, 0.0005), 0.0005]
        spec.worldbody.add_site(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, pos=center, size=half,
                                rgba=reg.get("rgba", [0, 0, 0, 0]), group=0 if "rgba" in reg else 5)


def add_cameras(spec: mujoco.MjSpec, cameras: list[dict], layout: Layout, u: Units, where: str) -> None:
    """The file's `[[camera]]`s, positions relative to the workspace centre on the table top."""
    cx, cy = layout.center
    for cam in cameras:
        w = f"{where}: [[camera]] '{cam['name']}'"
        rel = lengths(cam["pos"], 3, u, f"{w}: pos")
        eye = np.array([cx + rel[0], cy + rel[1], TABLE_TOP + rel[2]])
        kwargs: dict[str, Any] = {"name": cam["name"], "pos": eye, "fovy": float(cam.get("fovy", 45.0))}
        if "look_at" in cam:
            t = lengths(cam["look_at"], 3, u, f"{w}: look_at")
            target = np.array([cx + t[0], cy + t[1], TABLE_TOP + t[2]])
            if np.linalg.norm(target - eye) < 1e-6:
                raise TaskFileError(f"{w}: look_at: the camera looks at its own position")
            kwargs["xyaxes"] = look_at_xyaxes(eye, target)
        elif "xyaxes" in cam:
            kwargs["xyaxes"] = cam["xyaxes"]
        else:
            kwargs["quat"] = cam["quat"]
        spec.worldbody.add_camera(**kwargs)


def add_task_info(spec: mujoco.MjSpec, u: Units, bodies: list[str]) -> None:
    """What judging needs from the model alone: the units, and the objects' bodies (fixed ones included)."""
    spec.add_numeric(name=UNITS_NUMERIC, data=u.as_list(), size=4)
    spec.add_text(name=OBJECTS_TEXT, data=",".join(bodies))  # never empty


def add_object(spec: mujoco.MjSpec, obj: ObjectDef, geo: Geometry, pos: list[float], quat: list[float] | None,
               u: Units, assets: dict[str, bytes], aliases: dict[str, str]) -> None:
    """One object's body (free unless fixed) and geoms at `pos` (m, world)."""
    raw, name = obj.raw, obj.name
    fixed = bool(raw.get("fixed", False))
    rgba = raw.get("rgba", list(GREY) if obj.shape in ("bin", "mjcf") else [0.85, 0.2, 0.15, 1.0])
    friction = raw.get("friction", list(DEFAULT_FRICTION))
    friction = friction * 3 if len(friction) == 1 else friction
    collide = raw.get("collide", True)
    if obj.shape == "mjcf":
        frame = spec.worldbody.add_frame(pos=pos, **({"quat": quat} if quat is not None else {}))
        child = geo.mjcf.copy() if geo.mjcf is not None else mjcf_spec(obj, u)
        roots = [b.name for b in child.worldbody.bodies]
        prefix = f"{name}::"
        spec.attach(child, prefix=prefix, frame=frame)
        for group in (spec.bodies, spec.geoms, spec.sites, spec.joints, spec.cameras, spec.lights, spec.actuators,
                      spec.tendons, spec.equalities, spec.sensors, spec.excludes, spec.meshes, spec.materials, spec.textures):
            for e in group:
                if e.name.startswith(prefix):
                    e.name = e.name[len(prefix):]
        if roots and name not in roots:
            aliases[name] = roots[0]
        return
    body = spec.worldbody.add_body(name=name, pos=pos, **({"quat": quat} if quat is not None else {}))
    if not fixed:
        body.add_freejoint(name=f"{name}_joint")
    common: dict[str, Any] = {"rgba": rgba, "friction": friction}
    if not collide:
        common.update(contype=0, conaffinity=0)
    mass = raw.get("mass")
    density = raw.get("density")
    if obj.shape in ("box", "cylinder", "sphere", "capsule"):
        kind = {"box": mujoco.mjtGeom.mjGEOM_BOX, "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
                "sphere": mujoco.mjtGeom.mjGEOM_SPHERE, "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE}[obj.shape]
        n = {"box": 3, "cylinder": 2, "capsule": 2, "sphere": 1}[obj.shape]
        size = lengths(raw[obj.shape], n, u, f"{obj.where}: {obj.shape}")
        extra = {"mass": float(mass)} if mass is not None else {"density": float(density if density is not None else 600.0)}
        body.add_geom(name=f"{name}_geom", type=kind, size=size + [0.0] * (3 - n), condim=4, **common, **extra)
    elif obj.shape == "bin":
        hx, hy, height = lengths(raw["bin"], 3, u, f"{obj.where}: bin")
        wall = length(raw["wall"], u, f"{obj.where}: wall") if "wall" in raw else 0.004
        body.add_geom(name=f"{name}_floor", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx + wall, hy + wall, wall], pos=[0, 0, wall], **common)
        for i, (dx, dy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
            size = [wall, hy + wall, height / 2] if dx else [hx + wall, wall, height / 2]
            body.add_geom(name=f"{name}_wall{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=size,
                          pos=[dx * (hx + wall), dy * (hy + wall), height / 2], **common)
        body.add_site(name=f"{name}_inside", pos=[0, 0, height / 2], size=[hx, hy, height / 2], type=mujoco.mjtGeom.mjGEOM_BOX,
                      rgba=[0, 0, 0, 0], group=5)
    else:  # mesh: the mesh is seen, its convex parts collide
        visual_obj, part_objs = geo.obj_files()
        visual = f"task_{name}_visual.obj"
        assets[visual] = visual_obj
        spec.add_mesh(name=f"{name}_visual", file=visual, inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL)
        body.add_geom(name=f"{name}_visual", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}_visual", rgba=rgba,
                      contype=0, conaffinity=0, group=2, density=0.0)
        parts = geo.parts or []
        part_mass = {"mass": float(mass) / len(parts)} if mass is not None else {"density": float(density if density is not None else 400.0)}
        for i, data in enumerate(part_objs):
            file = f"task_{name}_part{i}.obj"
            assets[file] = data
            spec.add_mesh(name=f"{name}_part{i}", file=file)
            body.add_geom(name=f"{name}_col{i}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}_part{i}", group=3, condim=4,
                          **common, **part_mass)
