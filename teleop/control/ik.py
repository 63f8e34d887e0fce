"""Differential IK for one arm with mink, on an arm-only copy of the scene.

The IK model is the scene with every joint but this arm's removed (objects,
fingers and the other arm welded in place), so each solve works on exactly
the arm's degrees of freedom: a 7-DoF Panda solve is a 7-variable QP, not 15.
Limits are built once (mink rebuilds them on every call when given none).
mink's tasks and limits define the QP; `ArmQP` (ik_qp.py) assembles and solves
that same QP without mink's per-call stacking, to within 1e-9 of `mink.solve_ik`
(which stays the fallback for arms it does not handle, e.g. ball joints).
"""

from __future__ import annotations

import math

import mujoco
import mink
import numpy as np

from scenes import ArmSpec
from teleop.control.ik_qp import ArmQP, UnsupportedProblem

POSTURE_COST = 1e-2
LM_DAMPING = 1e-6
SOLVER_DAMPING = 1e-4
LIMIT_MARGIN = 0.03  # rad
LIMIT_GAIN = 0.3  # approach joint limits gradually: torque-limited joints cannot stop at once
MAX_JOINT_ACCEL = 30.0  # rad/s^2
MAX_JOINT_SPEED = 1.5  # rad/s: fast for teleop, slow enough that stiff servos do not overshoot


def arm_only_model(xml: str, assets: dict[str, bytes], arm: ArmSpec) -> mujoco.MjModel:
    """Compile the scene with only `arm`'s joints left movable."""
    spec = mujoco.MjSpec.from_string(xml, assets)
    spec.assets = dict(assets)
    for kind in (spec.actuators, spec.tendons, spec.equalities, spec.sensors, spec.keys):
        for element in list(kind):
            spec.delete(element)
    keep = set(arm.joints)
    for joint in list(spec.joints):
        if joint.name not in keep:
            spec.delete(joint)
    model = spec.compile()
    # Order of the kept joints in the IK model must match the arm's joint list.
    order = [model.joint(name).qposadr[0] for name in arm.joints]
    if order != list(range(len(arm.joints))):
        raise ValueError(f"arm joints {arm.joints} are not in kinematic order in the model")
    return model


class ArmIK:
    """Joint targets for one arm that bring its EE site to a world pose."""

    def __init__(self, xml: str, assets: dict[str, bytes], arm: ArmSpec, dt: float, table_geom: str | None = "table"):
        self.arm = arm
        self.dt = dt
        self.model = arm_only_model(xml, assets, arm)
        self.configuration = mink.Configuration(self.model)
        self.frame_task = mink.FrameTask(
            arm.ee_site, "site", position_cost=1.0, orientation_cost=arm.orientation_cost, lm_damping=LM_DAMPING
        )
        self.posture_task = mink.PostureTask(self.model, cost=POSTURE_COST)
        self.tasks = [self.frame_task, self.posture_task]
        self.limits: list = [
            # A margin inside the joint range, so the servo's small overshoot stays within it.
            mink.ConfigurationLimit(self.model, gain=LIMIT_GAIN, min_distance_from_limits=LIMIT_MARGIN),
            mink.VelocityLimit(self.model, {name: MAX_JOINT_SPEED for name in arm.joints}),
        ]
        hand_geoms = self._hand_geoms()
        if table_geom and hand_geoms and mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, table_geom) >= 0:
            self.limits.append(
                mink.CollisionAvoidanceLimit(
                    self.model, [(hand_geoms, [table_geom])], minimum_distance_from_collisions=0.004,
                    collision_detection_distance=0.03,
                )
            )
        ranges = self.model.jnt_range[: self.model.nq]
        limited = self.model.jnt_limited[: self.model.nq].astype(bool)
        self.q_min = np.where(limited, ranges[:, 0] + LIMIT_MARGIN / 2, -np.inf)
        self.q_max = np.where(limited, ranges[:, 1] - LIMIT_MARGIN / 2, np.inf)
        self.home = np.asarray(arm.home, dtype=float)
        self.accel_step = MAX_JOINT_ACCEL * dt  # rad/s of velocity change per solve
        self.target = mink.SE3.identity()  # the frame task's target, rewritten in place each solve
        self._target_quat, self._target_pos = self.target.wxyz_xyz[:4], self.target.wxyz_xyz[4:]  # views
        self._range = list(zip(self.q_min.tolist(), self.q_max.tolist()))  # (low, high) per joint, for the range check
        try:
            self.qp: ArmQP | None = ArmQP(
                self.configuration, self.frame_task, self.posture_task, self.limits, dt, SOLVER_DAMPING
            )
        except UnsupportedProblem:
            self.qp = None  # mink.solve_ik assembles it
        self.reset(self.home)

    def _hand_geoms(self) -> list[str]:
        """Named or anonymous geoms of the hand bodies, as mink wants: geom names or ids."""
        geoms: list = []
        for body in self.arm.hand_bodies:
            bid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, body)
            if bid < 0:
                continue
            for g in range(self.model.ngeom):
                if self.model.geom_bodyid[g] == bid and self.model.geom_contype[g] | self.model.geom_conaffinity[g]:
                    geoms.append(g)
        return geoms

    def reset(self, q: np.ndarray) -> None:
        """Start from joint positions `q` with the target at the resulting EE pose."""
        self.q = np.array(q, dtype=float)
        self.velocity = np.zeros_like(self.q)
        self.configuration.update(self.q)
        self.posture_task.set_target(self.home)
        self.frame_task.set_target(self.configuration.get_transform_frame_to_world(self.arm.ee_site, "site"))

    def ee_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """EE pose the current IK solution reaches (position, wxyz)."""
        T = self.configuration.get_transform_frame_to_world(self.arm.ee_site, "site")
        return T.translation().copy(), T.rotation().wxyz.copy()

    def solve(self, pos: np.ndarray, quat: np.ndarray) -> bool:
        """One IK step toward (pos, wxyz quat); False (and q unchanged) if it failed."""
        self._target_quat[:] = quat
        self._target_pos[:] = pos
        self.frame_task.transform_target_to_world = self.target
        velocity = self.qp.solve() if self.qp is not None else self._velocity()
        if velocity is None or not math.isfinite(velocity.dot(velocity)):  # NaN or inf in any entry
            self.configuration.update(self.q)
            self.velocity[:] = 0.0
            return False
        # Bounded acceleration: a joint that jumps to full speed in one tick whips
        # the rest of the arm (and past its limits) through inertial coupling.
        # (np.clip's results, by its ufuncs: np.clip costs a few microseconds more per call)
        step = self.accel_step
        np.maximum(velocity, self.velocity - step, out=velocity)
        np.minimum(velocity, self.velocity + step, out=velocity)
        # Configuration.integrate_inplace's calls, made here (the IK model has no equality constraints).
        model, data = self.model, self.configuration.data
        qpos = data.qpos
        mujoco.mj_integratePos(model, qpos, velocity, self.dt)
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        inside = True
        for value, (low, high) in zip(qpos.tolist(), self._range):
            if not low <= value <= high:  # outside, or NaN
                inside = False
                break
        if inside:  # the usual tick: the range clip below would change nothing
            self.velocity = velocity
            self.q = qpos.copy()
            return True
        q = np.minimum(np.maximum(qpos, self.q_min), self.q_max)
        if not math.isfinite(q.dot(q)):
            self.configuration.update(self.q)
            self.velocity[:] = 0.0
            return False
        if q.tolist() != qpos.tolist():  # finite: np.array_equal, in a quarter of the time
            self.configuration.update(q)
            velocity = (q - self.q) / self.dt
        self.velocity = velocity
        self.q = q
        return True

    def _velocity(self) -> np.ndarray | None:
        """The QP's joint velocity (rad/s) at the current configuration and targets; None if it failed."""
        if self.qp is not None:
            return self.qp.solve()
        try:
            return mink.solve_ik(self.configuration, self.tasks, self.dt, "daqp", damping=SOLVER_DAMPING, limits=self.limits)
        except Exception:  # infeasible QP or solver failure
            return None
