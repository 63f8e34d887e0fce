"""mink's IK problem for one fixed arm, assembled for speed and solved by daqp directly.

mink's FrameTask, PostureTask and limit objects define the problem and
`mink.solve_ik(configuration, [frame, posture], dt, "daqp", damping, limits=...)`
is the reference (tests/test_ik_fast.py compares the two). Per solve mink stacks
every task and limit into new arrays and goes through qpsolvers; on a fixed arm
(hinge and slide joints only, so q1 - q2 is the tangent difference) the same QP
is built with:

- buffers allocated once; the frame's pose and Jacobian read once, and its error,
  log Jacobian and weights taken as mink's FrameTask takes them (its compiled SE(3)
  operations where mink has them, else `FrameTask.compute_qp_residual`);
- the posture task's rows (cost * I) constant;
- configuration and velocity limits as daqp's box bounds on dq: their rows
  (+-I) never change, only the bounds do, so nothing is stacked;
- collision-avoidance rows only when a pair of geoms can be within the detection
  distance (a conservative bound: for a fixed box and geoms that move with the
  end-effector site, one point against one box); farther than that mink's rows
  are all zero with an infinite bound, and are left out;
- `daqp.solve` called directly.
"""

from __future__ import annotations

from ctypes import c_int

import daqp
import mink
import mujoco
import numpy as np

try:  # mink's compiled SE(3) operations (mink >= 1.3 on most platforms); the residual falls back to mink's own call
    from mink.lie import _lie_ops_c as se3_ops
except ImportError:  # pragma: no cover - depends on the installed mink
    se3_ops = None

INF = 1e30  # daqp's infinity (qpsolvers passes it for absent lower bounds)
HINGE_OR_SLIDE = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))


class UnsupportedProblem(ValueError):
    """The arm or limits fall outside what the fast path assembles; use mink.solve_ik."""


class PairFilter:
    """Whether any geom pair of a CollisionAvoidanceLimit might be within its detection distance.

    For a pair (a, b), b the geom with the larger bounding sphere: a lies within
    its bounding sphere (radius r_a) and b within its bounding box (geom_aabb, in
    b's frame), so if a's centre is, along some axis of b's frame, farther than
    half-size + r_a + detection distance from the box centre, the pair is farther
    apart than the detection distance and mink gives it no row (mj_geomDistance
    returns the cap). Planes, height fields and unbounded geoms are always near.

    When b never moves (welded to the world) and every a moves rigidly with the
    end-effector site, all the a geoms lie within one sphere around the site, so
    one point is tested against one box, in plain floats: the hand against the
    table, every tick. Otherwise each a's centre is tested (numpy).
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, limit: mink.CollisionAvoidanceLimit, site: int = -1):
        pairs = np.array(limit.geom_id_pairs, dtype=int).reshape(-1, 2)
        rbound = model.geom_rbound
        swap = rbound[pairs[:, 0]] > rbound[pairs[:, 1]]
        a = np.where(swap, pairs[:, 1], pairs[:, 0])
        b = np.where(swap, pairs[:, 0], pairs[:, 1])
        unbounded = [int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD)]
        kept = np.isin(model.geom_type[b], unbounded) | np.isin(model.geom_type[a], unbounded)
        kept |= rbound[a] <= 0.0
        self.always = bool(np.any(kept))
        margin = limit.collision_detection_distance + 1e-9  # m
        self.xpos, self.xmat = data.geom_xpos, data.geom_xmat  # views: MjData's buffers stay put
        self.site_xpos = data.site_xpos[site] if site >= 0 else None  # a view of the site's position
        weld = model.body_weldid
        site_weld = int(weld[model.site_bodyid[site]]) if site >= 0 else -1
        # Groups per box geom b. Point groups: (centre in world, axes as rows or None if the world's, reach per
        # axis), for a fixed box and a's that move with the site. Geom groups: (b, its a geoms, box centre in b's
        # frame or None if 0, per-pair reach per axis, b's orientation).
        self.points: list[tuple[tuple[float, float, float], list[list[float]] | None, tuple[float, float, float]]] = []
        self.groups = []
        for box in np.unique(b):
            others = a[b == box]
            center = model.geom_aabb[box, :3].copy()
            half = model.geom_aabb[box, 3:]
            rot = data.geom_xmat[box].reshape(3, 3)  # a view: b's orientation as the data holds it now
            fixed = int(weld[model.geom_bodyid[box]]) == 0
            if fixed and site_weld > 0 and all(int(weld[model.geom_bodyid[g]]) == site_weld for g in others):
                # Every a within `radius` of the site, whatever the arm's pose (they are welded to its body).
                radius = max(float(np.linalg.norm(data.geom_xpos[g] - self.site_xpos)) + float(rbound[g]) for g in others)
                world = data.geom_xpos[box] + rot @ center
                axes = None if np.array_equal(rot, np.eye(3)) else rot.T.tolist()
                reach = tuple(float(h) + radius + margin for h in half)
                self.points.append((tuple(world.tolist()), axes, reach))
                continue
            reach = half[None, :] + (rbound[others] + margin)[:, None]  # m, (pairs, 3)
            self.groups.append((int(box), others, center if np.any(center) else None, reach, rot))

    def any_near(self) -> bool:
        """True if some pair may be closer than the detection distance (geom poses as now in the data)."""
        if self.always:
            return True
        if self.points:
            x, y, z = self.site_xpos.tolist()
            for (cx, cy, cz), axes, (rx, ry, rz) in self.points:
                dx, dy, dz = x - cx, y - cy, z - cz
                if axes is not None:  # the offset in the box's frame
                    (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = axes
                    dx, dy, dz = a0 * dx + a1 * dy + a2 * dz, b0 * dx + b1 * dy + b2 * dz, c0 * dx + c1 * dy + c2 * dz
                if abs(dx) <= rx and abs(dy) <= ry and abs(dz) <= rz:
                    return True
        xpos = self.xpos
        for box, others, center, reach, rot in self.groups:
            local = xpos[others]  # a copy
            local -= xpos[box]
            local = local @ rot  # rows: a's centres in b's frame
            if center is not None:
                local -= center
            np.abs(local, out=local)
            local -= reach  # <= 0 on every axis: within reach (a - b <= 0 exactly when a <= b)
            if local.max(axis=1).min() <= 0.0:
                return True
        return False


class ArmQP:
    """The IK velocity of mink.solve_ik for a FrameTask + PostureTask and limits, fast.

    `solve()` reads the configuration and the tasks' targets as they are now and
    returns the tangent velocity (rad/s, m/s) or None if daqp found no solution.
    Raises UnsupportedProblem at construction for what it does not assemble
    (ball or free joints, other limit or task kinds, equality constraints).
    """

    def __init__(
        self,
        configuration: mink.Configuration,
        frame_task: mink.FrameTask,
        posture_task: mink.PostureTask,
        limits: list,
        dt: float,
        damping: float,
    ):
        model = configuration.model
        if model.nq != model.nv or any(int(t) not in HINGE_OR_SLIDE for t in model.jnt_type):
            raise UnsupportedProblem("only hinge and slide joints")
        if posture_task.lm_damping != 0.0:
            raise UnsupportedProblem("posture task with LM damping")
        nv = model.nv
        self.configuration = configuration
        self.model, self.data = model, configuration.data
        self.frame_task = frame_task
        self.posture_task = posture_task
        self.dt = dt
        self.damping = damping
        self.nv = nv
        self.site = -1
        if frame_task.frame_type == "site":
            self.site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, frame_task.frame_name)
        # mink's weighted frame residual read directly (site frames, its compiled SE(3) ops); else its own call
        self.direct = se3_ops is not None and self.site >= 0
        self.jac = np.empty((6, nv))  # the site's Jacobian, world-aligned (MuJoCo's)
        self.local = np.empty((6, nv))  # ... in the site's frame
        # Objective: W = [frame rows (6); posture rows (nv, constant)], e the weighted errors negated
        # (mink's c = -(e W) = (-e) W exactly: negation is exact). H = W'W + (damping + mu) I, f = e W.
        # The tasks' costs and gains are read here, once (nothing changes them after the IK is built).
        self.W = np.zeros((6 + nv, nv))
        self.W[6:] = posture_task.cost[:, None] * np.eye(nv)
        self.e = np.zeros(6 + nv)
        self.Jw, self.ew, self.pe = self.W[:6], self.e[:6], self.e[6:]  # views: frame task's Jw and -ew, posture's -ew
        self.negcost = -frame_task.cost[:, None]
        self.posture_scale = posture_task.gain * np.asarray(posture_task.cost, dtype=float)  # e's posture part / (q - q*)
        self.H = np.empty((nv, nv))
        self.f = np.empty(nv)
        self.diag = self.H.reshape(-1)[:: nv + 1]  # view of H's diagonal
        self.scratch = np.empty(nv)
        # Box bounds on dq: the velocity limits are constant, the configuration limits move with q.
        self.vel_bound = np.full(nv, INF)
        self.config: list[tuple[float, np.ndarray, np.ndarray]] = []  # (gain, upper, lower) per limit
        self.collisions: list[tuple[mink.CollisionAvoidanceLimit, PairFilter]] = []
        for limit in limits:
            if isinstance(limit, mink.ConfigurationLimit):
                upper = np.full(nv, INF)
                lower = np.full(nv, -INF)
                if len(limit.indices):
                    upper[limit.indices] = limit.upper[limit.indices]
                    lower[limit.indices] = limit.lower[limit.indices]
                self.config.append((float(limit.gain), upper, lower))
            elif isinstance(limit, mink.VelocityLimit):
                if len(limit.indices):
                    bound = dt * limit.limit
                    self.vel_bound[limit.indices] = np.minimum(self.vel_bound[limit.indices], bound)
            elif isinstance(limit, mink.CollisionAvoidanceLimit):
                self.collisions.append((limit, PairFilter(model, configuration.data, limit, self.site)))
            else:
                raise UnsupportedProblem(f"limit {type(limit).__name__}")
        rows = sum(limit.max_num_contacts for limit, _ in self.collisions)
        self.A = np.zeros((rows, nv))  # collision rows, filled only when near
        bounds = np.empty((2, nv + rows))  # daqp's upper and lower bounds, one row each
        bounds[1] = -INF
        self.bupper, self.blower = bounds[0], bounds[1]
        self.sense = np.zeros(nv + rows, dtype=c_int)
        self.box = bounds[:, :nv]  # the box part: rows upper, lower
        self.upper, self.lower = self.bupper[:nv], self.blower[:nv]  # views
        self.no_rows = (self.A[:0], self.bupper[:nv], self.blower[:nv], self.sense[:nv])  # daqp's arguments, no collision rows
        self.neg_vel_bound = -self.vel_bound
        # One configuration limit (the usual case): both sides of the box at once. Rows [hi; lo] - q, times gain,
        # are gain * (hi - q) and gain * (lo - q) = -(gain * (q - lo)) exactly (a - b = -(b - a) in IEEE), so
        # min(vel, the first) and max(-vel, the second) are mink's rows' bounds dq <= .. and -dq <= .. negated.
        if len(self.config) == 1:
            gain, hi, lo = self.config[0]
            self.range2 = np.stack([hi, lo])
            self.gain = gain

    def _bounds(self, q: np.ndarray) -> None:
        """Box on dq: velocity limits and, per configuration limit, gain * distance to the range.

        The lower bound is kept negated (as mink's row -dq <= gain * (q - lo)) until the end.
        """
        upper, lower, s = self.upper, self.lower, self.scratch
        if not self.config:
            upper[:] = self.vel_bound
            np.negative(self.vel_bound, out=lower)
            return
        if len(self.config) == 1:
            box = self.box
            np.subtract(self.range2, q, out=box)
            box *= self.gain
            np.minimum(self.vel_bound, upper, out=upper)
            np.maximum(self.neg_vel_bound, lower, out=lower)
            return
        for i, (gain, hi, lo) in enumerate(self.config):
            np.subtract(hi, q, out=s)
            s *= gain
            np.minimum(self.vel_bound if i == 0 else upper, s, out=upper)
            np.subtract(q, lo, out=s)
            s *= gain
            np.minimum(self.vel_bound if i == 0 else lower, s, out=lower)
        np.negative(lower, out=lower)

    def _collision_rows(self) -> int:
        """mink's collision rows that bind (finite bound) into A; how many."""
        m = 0
        configuration = self.configuration
        for limit, near in self.collisions:
            if not near.any_near():
                continue
            G, h = limit.compute_qp_inequalities(configuration, self.dt)
            active = np.flatnonzero(h < np.inf)
            k = len(active)
            if k:
                self.A[m : m + k] = G[active]
                self.bupper[self.nv + m : self.nv + m + k] = h[active]
                m += k
        return m

    def _frame_residual(self) -> float:
        """The frame task's weighted Jacobian into Jw and negated weighted error into ew; mink's LM term mu.

        As FrameTask.compute_qp_residual: e = log(T_bt) (body twist), J = -jlog(T_tb) A J_site, then
        cost * J and cost * (-gain * e); computed from the site's pose and Jacobian read once."""
        task = self.frame_task
        if not self.direct:
            weighted_jacobian, weighted_error, mu = task.compute_qp_residual(self.configuration)
            self.Jw[:] = weighted_jacobian
            np.negative(weighted_error, out=self.ew)
            return mu
        data, site, jac, ops = self.data, self.site, self.jac, se3_ops
        xmat = data.site_xmat[site]
        frame = ops.xmat_xpos_to_wxyz_xyz(xmat, data.site_xpos[site])
        target = task.transform_target_to_world.wxyz_xyz
        error = ops.se3_rminus(target, frame)
        jlog = ops.se3_jlog(ops.se3_inverse_multiply(target, frame))
        mujoco.mj_jacSite(self.model, data, jac[:3], jac[3:], site)
        np.matmul(ops.se3_rotation_adjoint_from_xmat(xmat), jac, out=self.local)  # in the site's frame
        np.matmul(jlog, self.local, out=self.Jw)  # -(-jlog @ J): negated below with the cost
        cost = task.cost
        self.Jw *= self.negcost
        ew = self.ew
        if task.gain == 1.0:  # -(cost * (-1.0 * e)) = cost * e exactly
            np.multiply(cost, error, out=ew)
        else:
            np.multiply(error, -task.gain, out=ew)
            ew *= cost
            np.negative(ew, out=ew)
        return task.lm_damping * float(ew.dot(ew))

    def solve(self) -> np.ndarray | None:
        """Tangent velocity toward the tasks' targets under the limits; None if infeasible."""
        nv, H, f, W = self.nv, self.H, self.f, self.W
        q = self.data.qpos
        mu = self._frame_residual()
        # Posture rows cost * I, error cost * gain * (q - q*) (the tangent difference for hinge/slide joints).
        pe = self.pe
        np.subtract(q, self.posture_task.target_q, out=pe)
        pe *= self.posture_scale
        np.matmul(W.T, W, out=H)
        self.diag += self.damping + mu
        np.matmul(self.e, W, out=f)
        self._bounds(q)
        m = self._collision_rows() if self.collisions else 0
        if m:
            n = nv + m
            x, _, exitflag, _ = daqp.solve(H, f, self.A[:m], self.bupper[:n], self.blower[:n], self.sense[:n])
        else:
            x, _, exitflag, _ = daqp.solve(H, f, *self.no_rows)
        if exitflag <= 0:
            return None
        x /= self.dt
        return x
