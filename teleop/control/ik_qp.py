"""mink's IK problem for one fixed arm, assembled for speed and solved by daqp directly.

mink's FrameTask, PostureTask and limit objects define the problem and
`mink.solve_ik(configuration, [frame, posture], dt, "daqp", damping, limits=...)`
is the reference (tests/test_ik_fast.py compares the two). Per solve mink stacks
every task and limit into new arrays and goes through qpsolvers; on a fixed arm
(hinge and slide joints only, so q1 - q2 is the tangent difference) the same QP
is built with:

- buffers allocated once; the frame task's Jacobian and error taken once
  (`FrameTask.compute_qp_residual`); the posture rows (cost * I) constant;
- configuration and velocity limits as daqp's box bounds on dq: their rows
  (+-I) never change, only the bounds do, so nothing is stacked;
- collision-avoidance rows only when a pair of geoms can be within the detection
  distance (a conservative bound from bounding spheres and boxes); farther than
  that mink's rows are all zero with an infinite bound, and are left out;
- `daqp.solve` called directly.
"""

from __future__ import annotations

from ctypes import c_int

import daqp
import mink
import mujoco
import numpy as np

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
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, limit: mink.CollisionAvoidanceLimit):
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
        # One group per box geom b: (b, its a geoms, box centre in b's frame or None if 0, per-pair reach per axis).
        self.groups = []
        for box in np.unique(b):
            others = a[b == box]
            center = model.geom_aabb[box, :3].copy()
            reach = model.geom_aabb[box, 3:][None, :] + (rbound[others] + margin)[:, None]  # m, (pairs, 3)
            rot = data.geom_xmat[box].reshape(3, 3)  # a view: b's orientation as the data holds it now
            self.groups.append((int(box), others, center if np.any(center) else None, reach, rot))

    def any_near(self) -> bool:
        """True if some pair may be closer than the detection distance (geom poses as now in the data)."""
        if self.always:
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
        self.frame_task = frame_task
        self.posture_task = posture_task
        self.dt = dt
        self.damping = damping
        self.nv = nv
        # Objective: W = [frame rows (6); posture rows (nv, constant)], e the weighted errors
        # negated (mink's c = -(e W) = (-e) W exactly: negation is exact).
        self.W = np.zeros((6 + nv, nv))
        self.W[6:] = posture_task.cost[:, None] * np.eye(nv)
        self.e = np.zeros(6 + nv)
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
                self.collisions.append((limit, PairFilter(model, configuration.data, limit)))
            else:
                raise UnsupportedProblem(f"limit {type(limit).__name__}")
        rows = sum(limit.max_num_contacts for limit, _ in self.collisions)
        self.A = np.zeros((rows, nv))  # collision rows, filled only when near
        self.bupper = np.empty(nv + rows)
        self.blower = np.full(nv + rows, -INF)
        self.sense = np.zeros(nv + rows, dtype=c_int)
        self.upper = self.bupper[:nv]  # views: the box part
        self.lower = self.blower[:nv]

    def _bounds(self, q: np.ndarray) -> None:
        """Box on dq: velocity limits and, per configuration limit, gain * distance to the range.

        The lower bound is kept negated (as mink's row -dq <= gain * (q - lo)) until the end.
        """
        upper, lower, s = self.upper, self.lower, self.scratch
        if not self.config:
            upper[:] = self.vel_bound
            np.negative(self.vel_bound, out=lower)
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

    def solve(self) -> np.ndarray | None:
        """Tangent velocity toward the tasks' targets under the limits; None if infeasible."""
        configuration, nv, W, e, H, f = self.configuration, self.nv, self.W, self.e, self.H, self.f
        q = configuration.data.qpos
        weighted_jacobian, weighted_error, mu = self.frame_task.compute_qp_residual(configuration)
        W[:6] = weighted_jacobian
        np.negative(weighted_error, out=e[:6])
        posture = self.posture_task
        err = e[6:]
        np.subtract(q, posture.target_q, out=err)  # q - q*: the tangent difference for hinge/slide
        if posture.gain != 1.0:
            err *= posture.gain
        err *= posture.cost  # -(cost * (-gain * (q - q*)))
        np.matmul(W.T, W, out=H)
        self.diag += self.damping + mu
        np.matmul(e, W, out=f)
        self._bounds(q)
        m = self._collision_rows() if self.collisions else 0
        n = nv + m
        x, _, exitflag, _ = daqp.solve(H, f, self.A[:m], self.bupper[:n], self.blower[:n], self.sense[:n])
        if exitflag <= 0:
            return None
        x /= self.dt
        return x
