"""Physics variation, sampled when a scene is built and written into its model, so a replay is bit-exact.

Applies to the task's own bodies (the world's children the task added): free objects
get a size factor (geoms, sites and meshes scaled about the body's origin, the body
raised or lowered so that it still stands where it stood, on the table or on what
it stood on), a mass factor and a sliding-friction factor; articulated joints
(hinges and slides of drawers, doors) a damping factor; physical distractors are
added as free bodies. Every draw comes from the one generator given, in a fixed
order, so the same seed gives the same parameters (scenes.vary.variation.physics_rng).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from scenes.vary import distractors
from scenes.vary.variation import Ranges, uniform

SUPPORT_GAP = 0.003  # m: an object whose bottom lies this close to another's top stands on it


def _free(body: mujoco.MjsBody) -> bool:
    return any(int(j.type) == int(mujoco.mjtJoint.mjJNT_FREE) for j in body.joints)


def _extents(model: mujoco.MjModel, data: mujoco.MjData, root: int) -> tuple[float, float, np.ndarray, float]:
    """(bottom z, top z, xy centre, xy radius) of the geoms of body tree `root`, world frame, m."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for g in np.flatnonzero(model.body_rootid[model.geom_bodyid] == root):
        rot = data.geom_xmat[g].reshape(3, 3)
        center = data.geom_xpos[g] + rot @ model.geom_aabb[g, :3]
        half = np.abs(rot) @ model.geom_aabb[g, 3:]
        lo, hi = np.minimum(lo, center - half), np.maximum(hi, center + half)
    if not np.all(np.isfinite(lo)):
        x, y = data.xpos[root][:2]
        return float(data.xpos[root][2]), float(data.xpos[root][2]), np.array([x, y]), 0.0
    return float(lo[2]), float(hi[2]), (lo[:2] + hi[:2]) / 2, float(np.linalg.norm(hi[:2] - lo[:2]) / 2)


def _scale(spec: mujoco.MjSpec, body: mujoco.MjsBody, f: float) -> None:
    """Scale every geom, site and mesh of `body`'s tree by `f` about the body's origin."""
    meshes = set()
    for geom in body.find_all(mujoco.mjtObj.mjOBJ_GEOM):
        geom.size = np.asarray(geom.size) * f
        geom.pos = np.asarray(geom.pos) * f
        if not np.isnan(geom.fromto[0]):
            geom.fromto = np.asarray(geom.fromto) * f
        if geom.meshname:
            meshes.add(geom.meshname)
    for site in body.find_all(mujoco.mjtObj.mjOBJ_SITE):
        site.size = np.asarray(site.size) * f
        site.pos = np.asarray(site.pos) * f
    for child in body.find_all(mujoco.mjtObj.mjOBJ_BODY):
        child.pos = np.asarray(child.pos) * f
    for joint in body.find_all(mujoco.mjtObj.mjOBJ_JOINT):
        joint.pos = np.asarray(joint.pos) * f
    for mesh in spec.meshes:
        if mesh.name in meshes:
            mesh.scale = np.asarray(mesh.scale) * f


def _reweigh(body: mujoco.MjsBody, f: float) -> None:
    """Multiply the tree's mass by `f`: each geom's mass where given, else its density."""
    for geom in body.find_all(mujoco.mjtObj.mjOBJ_GEOM):
        if not np.isnan(geom.mass):
            geom.mass = float(geom.mass) * f
        else:
            geom.density = float(geom.density) * f


def _restand(spec: mujoco.MjSpec, before: mujoco.MjModel, names: Sequence[str]) -> None:
    """After scaling: move each task body vertically so it stands on what it stood on (lowest first)."""
    after = spec.compile()
    d0, d1 = mujoco.MjData(before), mujoco.MjData(after)
    mujoco.mj_kinematics(before, d0)
    mujoco.mj_kinematics(after, d1)
    info0 = {n: _extents(before, d0, before.body(n).id) for n in names}
    info1 = {n: _extents(after, d1, after.body(n).id) for n in names}
    shift: dict[str, float] = {}
    for name in sorted(names, key=lambda n: info0[n][0]):
        bottom, _, xy, _ = info0[name]
        under = [o for o in shift if abs(info0[o][1] - bottom) < SUPPORT_GAP
                 and np.linalg.norm(info0[o][2] - xy) < info0[o][3] + 1e-3]
        target = max(info1[o][1] + shift[o] for o in under) if under else bottom
        shift[name] = target - info1[name][0]
        if abs(shift[name]) > 1e-12:
            body = spec.body(name)
            pos = np.asarray(body.pos, float)
            pos[2] += shift[name]
            body.pos = pos


def vary_physics(spec: mujoco.MjSpec, task_roots: Sequence[str], robot_roots: Sequence[str], kinds: Sequence[str],
                 ranges: Ranges, rng: np.random.Generator) -> dict[str, Any]:
    """Draw and apply the physics `kinds` to the task bodies `task_roots` of an arena spec; returns what was drawn.

    Factors are rounded to 4 decimals (the model XML keeps 6 digits, so the recorded
    parameters are the ones the episode's model holds). JSON: {"size": {object: f},
    "mass": {...}, "friction": {...}, "damping": {joint: f}, "distractors": [...]}.
    """
    before = spec.compile()
    free = [n for n in task_roots if _free(spec.body(n))]
    params: dict[str, Any] = {}
    for kind in ("size", "mass", "friction"):
        if kind in kinds:
            params[kind] = {n: round(uniform(rng, getattr(ranges, kind)), 4) for n in free}
    if "damping" in kinds:
        joints = []
        for n in task_roots:
            for j in spec.body(n).find_all(mujoco.mjtObj.mjOBJ_JOINT):
                if int(j.type) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)) and j.name:
                    joints.append(j)
        params["damping"] = {j.name: round(uniform(rng, ranges.damping), 4) for j in joints}
        for j in joints:
            j.damping = np.asarray(j.damping, float) * params["damping"][j.name]
    for name in free:
        body = spec.body(name)
        if "size" in params:
            _scale(spec, body, params["size"][name])
        if "mass" in params:
            _reweigh(body, params["mass"][name])
        if "friction" in params:
            for geom in body.find_all(mujoco.mjtObj.mjOBJ_GEOM):
                friction = np.asarray(geom.friction, float)
                friction[0] *= params["friction"][name]
                geom.friction = friction
    if "size" in params and free:
        _restand(spec, before, task_roots)
    if "distractors" in kinds:
        model = spec.compile()
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        area = distractors.area_of(model)
        roots = {model.body(n).id for n in robot_roots if n}
        params["distractors"] = distractors.sample(rng, ranges, area, distractors.obstacles(model, data, roots, area.reach))
        for d in params["distractors"]:
            distractors.add(spec, d, physical=True)
    return params


__all__ = ["vary_physics"]
