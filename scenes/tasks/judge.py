"""A parsed success expression bound to one compiled model: the predicates, evaluated on MjData.

Names resolve once per model (object aliases first, then body, site, geom;
joints for open/closed). Lengths with a layout unit read the units the scene
stored in the model (custom numeric UNITS_NUMERIC: size, spread, reach, scale,
all m except scale); plain numbers are multiplied by the task's scale. Geometry
(footprints, heights, container boxes) comes from the model's geoms, in each
body's own frame, so a recording's model alone is enough to judge it again.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import mujoco
import numpy as np

from scenes.errors import TeleopError
from scenes.tasks.expr import PREDICATES, And, Node, Not, Number, Pred
from scenes.tasks.geometry import Units, body_box, colliding_geom, subtree

REST_SPEED = 0.05  # m/s: at_rest below this linear speed


class JudgeError(TeleopError):
    """A success expression that names something the scene does not have."""


class Judge:
    """`expr` evaluated against `model`; `aliases` maps task object names to body names."""

    def __init__(self, expr: Node, model: mujoco.MjModel, units: Units, aliases: Mapping[str, str] | None = None,
                 task_bodies: tuple[str, ...] = ()) -> None:
        self.expr, self.model, self.units = expr, model, units
        self.aliases = dict(aliases or {})
        self._data0 = mujoco.MjData(model)
        mujoco.mj_kinematics(model, self._data0)
        objects = set()
        for name in task_bodies:
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, self.aliases.get(name, name))
            if b >= 0:
                objects |= subtree(model, b)
        self._robot = {b for b in range(1, model.nbody) if b not in objects}
        self._cache: dict[tuple, object] = {}
        self._check(expr)
        self._call = self._compile(expr)

    # -- names -----------------------------------------------------------------------
    def _ref(self, name: str) -> tuple[int, int]:
        """(mjtObj kind, id) of a body, site or geom named `name` (object names first)."""
        key = ("ref", name)
        if key not in self._cache:
            target = self.aliases.get(name, name)
            for kind in (mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_SITE, mujoco.mjtObj.mjOBJ_GEOM):
                i = mujoco.mj_name2id(self.model, kind, target)
                if i >= 0:
                    self._cache[key] = (kind, i)
                    break
            else:
                raise JudgeError(f"success: the scene has no object, body, site or geom named {name!r}")
        return self._cache[key]  # type: ignore[return-value]

    def _joint(self, name: str) -> int:
        j = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if j < 0:
            raise JudgeError(f"success: the scene has no joint named {name!r}")
        if int(self.model.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            raise JudgeError(f"success: joint {name!r} is not a hinge or slide joint")
        return j

    def _check(self, node: Node) -> None:
        if isinstance(node, Pred):
            for arg, kind in zip(node.args, _kinds(node)):
                if kind == "joint":
                    self._joint(str(arg))
                elif kind == "name":
                    self._ref(str(arg))
        elif isinstance(node, Not):
            self._check(node.arg)
        else:
            for a in node.args:
                self._check(a)

    def _body(self, name: str) -> int:
        kind, i = self._ref(name)
        if kind == mujoco.mjtObj.mjOBJ_BODY:
            return i
        return int((self.model.site_bodyid if kind == mujoco.mjtObj.mjOBJ_SITE else self.model.geom_bodyid)[i])

    def _pos(self, data: mujoco.MjData, name: str, initial: bool = False) -> np.ndarray:
        kind, i = self._ref(name)
        d = self._data0 if initial else data
        if kind == mujoco.mjtObj.mjOBJ_BODY:
            return d.xpos[i]
        return d.site_xpos[i] if kind == mujoco.mjtObj.mjOBJ_SITE else d.geom_xpos[i]

    def _frame(self, data: mujoco.MjData, name: str) -> tuple[np.ndarray, np.ndarray]:
        kind, i = self._ref(name)
        if kind == mujoco.mjtObj.mjOBJ_BODY:
            return data.xpos[i], data.xmat[i].reshape(3, 3)
        if kind == mujoco.mjtObj.mjOBJ_SITE:
            return data.site_xpos[i], data.site_xmat[i].reshape(3, 3)
        return data.geom_xpos[i], data.geom_xmat[i].reshape(3, 3)

    def _box(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) of `name`'s volume in its own frame: a box site's box, else its geoms' box."""
        key = ("box", name)
        if key not in self._cache:
            kind, i = self._ref(name)
            m = self.model
            if kind == mujoco.mjtObj.mjOBJ_SITE:
                s = m.site_size[i]
                box = (-s.copy(), s.copy())
            elif kind == mujoco.mjtObj.mjOBJ_GEOM:
                c, h = m.geom_aabb[i, :3], m.geom_aabb[i, 3:]
                box = (c - h, c + h)
            else:
                box = body_box(m, subtree(m, i), i)
                if not np.any(box[1] - box[0]):  # a visual-only body (a target mark): its drawn geoms are its extent
                    box = body_box(m, subtree(m, i), i, colliding=False)
            self._cache[key] = box
        return self._cache[key]  # type: ignore[return-value]

    def _inner(self, name: str) -> str:
        """A container's inner volume: box site `name` or `name_inside` when the model has one, else `name`."""
        for candidate in (self.aliases.get(name, name), f"{name}_inside"):
            if mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, candidate) >= 0:
                return candidate
        return name

    # -- evaluation ------------------------------------------------------------------
    def __call__(self, data: mujoco.MjData) -> bool:
        return self._call(data)

    def bound(self, data: mujoco.MjData) -> Callable[[], bool]:
        """The test on `data` alone, with its arrays looked up once (an MjData's arrays keep their memory):
        for the control tick, which judges a task with a `hold` every tick."""
        return self._compile_bound(self.expr, data)

    def _compile_bound(self, node: Node, data: mujoco.MjData) -> Callable[[], bool]:
        if isinstance(node, Pred) and node.name == "lifted":
            height, floor = self._lifted_parts(node, data)
            return lambda: bool(height[2] > floor)
        if isinstance(node, Pred):
            fn, args = getattr(self, f"_p_{node.name}"), tuple(node.args)
            return lambda: bool(fn(data, *args))
        if isinstance(node, Not):
            inner = self._compile_bound(node.arg, data)
            return lambda: not inner()
        parts = [self._compile_bound(a, data) for a in sorted(node.args, key=_cost)]
        if len(parts) == 1:
            return parts[0]
        if len(parts) == 2:
            first, second = parts
            cheap = sorted(node.args, key=_cost)[0]
            if isinstance(node, And) and isinstance(cheap, Pred) and cheap.name == "lifted":  # the usual hold test
                height, floor = self._lifted_parts(cheap, data)
                return lambda: bool(height[2] > floor) and second()
            if isinstance(node, And):
                return lambda: first() and second()
            return lambda: first() or second()
        if isinstance(node, And):
            return lambda: all(part() for part in parts)
        return lambda: any(part() for part in parts)

    def _lifted_parts(self, node: Pred, data: mujoco.MjData) -> tuple[np.ndarray, float]:
        """(the object's world position: a view into `data`, the height (m) it must pass)."""
        a, h = node.args
        floor = float(self._pos(self._data0, str(a), initial=True)[2] + self.units.length(h))
        return self._pos(data, str(a)), floor

    def _compile(self, node: Node) -> Callable[[mujoco.MjData], bool]:
        """The expression as nested closures, made once. Judged every control tick (a task with a `hold`),
        so the operands of `and` / `or` are tried cheapest first: the predicates have no side effects, so
        the answer is the same, and `grasped(cube) and lifted(cube, 0.05)` costs a height comparison on
        every tick the cube is on the table instead of a pass over the contacts (~40 us a tick)."""
        if isinstance(node, Pred):
            if node.name == "lifted":  # the commonest test, made a single comparison
                a, h = node.args
                kind, i = self._ref(str(a))
                floor = float(self._pos(self._data0, str(a), initial=True)[2] + self.units.length(h))
                field = {mujoco.mjtObj.mjOBJ_BODY: "xpos", mujoco.mjtObj.mjOBJ_SITE: "site_xpos"}.get(kind, "geom_xpos")
                return lambda data: bool(getattr(data, field)[i, 2] > floor)
            fn, args = getattr(self, f"_p_{node.name}"), tuple(node.args)
            return lambda data: bool(fn(data, *args))
        if isinstance(node, Not):
            inner = self._compile(node.arg)
            return lambda data: not inner(data)
        parts = [self._compile(a) for a in sorted(node.args, key=_cost)]
        if len(parts) == 1:
            return parts[0]
        if len(parts) == 2:
            first, second = parts
            if isinstance(node, And):
                return lambda data: first(data) and second(data)
            return lambda data: first(data) or second(data)
        if isinstance(node, And):
            return lambda data: all(part(data) for part in parts)
        return lambda data: any(part(data) for part in parts)

    def _p_lifted(self, data, a, h) -> bool:
        key = ("lifted", a, h)
        floor = self._cache.get(key)
        if floor is None:  # the height to pass: the initial height plus h (m), found once
            floor = self._cache[key] = float(self._pos(data, a, initial=True)[2] + self.units.length(h))
        return bool(self._pos(data, a)[2] > floor)

    def _p_near(self, data, a, b, d) -> bool:
        return bool(np.linalg.norm(self._pos(data, a) - self._pos(data, b)) < self.units.length(d))

    def _p_upright(self, data, a, tol) -> bool:
        _, rot = self._frame(data, a)
        return bool(np.arccos(np.clip(rot[2, 2], -1.0, 1.0)) < self.units.angle(tol))

    def _p_at_rest(self, data, a) -> bool:
        body = self._body(a)
        jnt = int(self.model.body_jntadr[body])
        if jnt >= 0 and int(self.model.jnt_type[jnt]) == int(mujoco.mjtJoint.mjJNT_FREE):
            dof = int(self.model.jnt_dofadr[jnt])
            return bool(np.linalg.norm(data.qvel[dof:dof + 3]) < REST_SPEED)
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, data, mujoco.mjtObj.mjOBJ_BODY, body, vel, 0)
        return bool(np.linalg.norm(vel[3:]) < REST_SPEED)

    def _amount(self, j: int, f: Number) -> float:
        lo, hi = self.model.jnt_range[j]
        if f.unit == "":
            return float(f.value * (hi - lo))
        if f.unit in ("deg", "rad"):
            return Units.angle(f)
        return self.units.length(f)

    def _p_open(self, data, joint, f) -> bool:
        j = self._joint(joint)
        return bool(data.qpos[self.model.jnt_qposadr[j]] > self.model.jnt_range[j][0] + self._amount(j, f))

    def _p_closed(self, data, joint, f) -> bool:
        j = self._joint(joint)
        return bool(data.qpos[self.model.jnt_qposadr[j]] < self.model.jnt_range[j][0] + self._amount(j, f))

    def _p_inside(self, data, a, c) -> bool:
        inner = self._inner(c)
        lo, hi = self._box(inner)
        origin, rot = self._frame(data, inner)
        local = rot.T @ (self._pos(data, a) - origin)
        return bool(np.all(local > lo) and np.all(local < hi))

    def _p_in_region(self, data, a, r) -> bool:
        lo, hi = self._box(r)
        origin, rot = self._frame(data, r)
        local = rot.T @ (self._pos(data, a) - origin)
        return bool(np.all(local[:2] > lo[:2]) and np.all(local[:2] < hi[:2]))

    def _p_on(self, data, a, b) -> bool:
        """a's centre is over b's footprint and a's bottom lies on b's surface under it (within a quarter of a's half-height)."""
        m = self.model
        b_body = self._body(b) if self._ref(b)[0] == mujoco.mjtObj.mjOBJ_BODY else None
        alo, ahi = self._box(a) if self._ref(a)[0] != mujoco.mjtObj.mjOBJ_SITE else (np.zeros(3), np.zeros(3))
        apos, arot = self._frame(data, a)
        center = apos + arot @ ((alo + ahi) / 2)
        half_h = (ahi[2] - alo[2]) / 2
        blo, bhi = self._box(b)
        bpos, brot = self._frame(data, b)
        bcenter = bpos + brot @ ((blo + bhi) / 2)
        reach = min(bhi[0] - blo[0], bhi[1] - blo[1]) / 2
        if np.linalg.norm(center[:2] - bcenter[:2]) >= reach:
            return False
        geoms = ([g for g in range(m.ngeom) if int(m.geom_bodyid[g]) in subtree(m, b_body) and colliding_geom(m, g)]
                 if b_body is not None else [self._ref(b)[1]])
        down = np.array([0.0, 0.0, -1.0])
        best = np.inf
        for g in geoms:
            if int(m.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_MESH):
                dist = mujoco.mj_rayMesh(m, data, g, center, down)
            else:
                dist = mujoco.mju_rayGeom(data.geom_xpos[g], data.geom_xmat[g], m.geom_size[g], center, down, int(m.geom_type[g]))
            if dist >= 0:
                best = min(best, dist)
        if not np.isfinite(best):
            return False
        return bool(abs(best - half_h) < 0.25 * half_h)

    def _p_grasped(self, data, a) -> bool:
        """a touches two or more robot bodies (both fingers of a gripper).

        Checked every control tick, so on arrays: each contact's two bodies, looked up in a
        per-object mask of a's bodies and one of the robot's (a loop over MjContact structs
        cost ~0.3 ms a tick)."""
        n = data.ncon
        if n == 0:
            return False
        mine, robot = self._grasp_masks(a)
        bodies = self.model.geom_bodyid[data.contact.geom[:n]]  # (n, 2)
        b1, b2 = bodies[:, 0], bodies[:, 1]
        touching = set(b2[mine[b1] & robot[b2]].tolist())
        touching.update(b1[mine[b2] & robot[b1]].tolist())
        return len(touching) >= 2

    def _grasp_masks(self, a: str) -> tuple[np.ndarray, np.ndarray]:
        """(a's bodies, the robot's bodies) as boolean arrays over the model's bodies."""
        key = ("grasp", a)
        if key not in self._cache:
            m = self.model
            mine = np.zeros(m.nbody, bool)
            mine[list(subtree(m, self._body(a)))] = True
            robot = np.zeros(m.nbody, bool)
            robot[list(self._robot)] = True
            self._cache[key] = (mine, robot)
        return self._cache[key]  # type: ignore[return-value]


def _kinds(pred: Pred) -> tuple[str, ...]:
    return PREDICATES[pred.name]


# Relative cost of judging each predicate: a position or joint read first, boxes next, contacts and rays last.
_PREDICATE_COST = {"lifted": 1, "near": 1, "upright": 1, "open": 1, "closed": 1, "at_rest": 2,
                   "inside": 3, "in_region": 3, "grasped": 5, "on": 8}


def _cost(node: Node) -> int:
    """How dear a sub-expression is to judge (the sum over its predicates; unknown ones are dear)."""
    if isinstance(node, Pred):
        return _PREDICATE_COST.get(node.name, 10)
    if isinstance(node, Not):
        return _cost(node.arg)
    return sum(_cost(a) for a in node.args)
