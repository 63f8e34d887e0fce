"""The control tick: device commands -> EE targets -> clamp -> IK -> joint targets -> physics.

A `Controller` drives one compiled scene. It knows nothing of files: whoever
wants to record a tick passes an observer, called once before ctrl is written
(the state then is what replay restores) and once after physics. Only ctrl and
mj_step touch the physics MjData, which is what makes recordings replay bit
for bit.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import mujoco
import numpy as np
from mujoco import mju_dist3

from devices.command import Command
from scenes import Scene, actuator_for_joint
from scenes.assembly.arena import TABLE_TOP
from scenes.numbers import number_or_nan
from teleop.control.ik import ArmIK

TRACKING_HISTORY = 200_000  # ticks (about 2 h at 30 Hz)
MAX_PHYSICS_STEP = 0.002  # s; the control period is split into equal steps no longer than this


def physics_split(control_hz: float) -> tuple[int, float]:
    """Substeps per control tick and the physics timestep (s) that makes the rate exact."""
    period = 1.0 / control_hz
    substeps = max(1, math.ceil(period / MAX_PHYSICS_STEP - 1e-9))
    return substeps, period / substeps


def norm(v: np.ndarray) -> float:
    """Euclidean norm of a float vector, bit for bit np.linalg.norm's (sqrt of v.v) without its overhead."""
    return math.sqrt(v.dot(v))


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of two wxyz quaternions."""
    out = np.empty(4)
    mujoco.mju_mulQuat(out, a, b)
    return out


IDENTITY_QUAT = np.array([1.0, 0.0, 0.0, 0.0])
IDENTITY_QUAT.setflags(write=False)


def axis_angle_quat(rotvec: np.ndarray) -> np.ndarray:
    """wxyz quaternion of an axis-angle vector (radians); read-only when it is the identity."""
    angle = norm(rotvec)
    if angle < 1e-12:
        return IDENTITY_QUAT
    out = np.empty(4)
    mujoco.mju_axisAngle2Quat(out, np.asarray(rotvec, float) / angle, angle)
    return out


@dataclass
class ArmState:
    """One arm's IK, its EE target (world frame, m and wxyz) and gripper.

    joint_hold: joint targets (rad) a joint command set, written to ctrl instead of IK's
    until an EE command arrives (None: IK drives). gripper_ctrl: the gripper actuator's
    ctrl a `gripper_opening` set (None: open or closed as `gripper_open` says).
    """

    ik: ArmIK
    site_id: int
    ctrl_ids: np.ndarray  # actuator index per arm joint
    gripper_id: int | None
    ctrl_index: slice | np.ndarray | None = None  # ctrl_ids as a slice when they run in order (a cheaper write)
    target_pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    target_quat: np.ndarray = field(default_factory=lambda: np.array([1.0, 0, 0, 0]))
    gripper_open: bool = True
    qpos_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # qpos index per arm joint
    joint_lo: np.ndarray = field(default_factory=lambda: np.zeros(0))  # rad, joint range (-inf: unlimited)
    joint_hi: np.ndarray = field(default_factory=lambda: np.zeros(0))
    joint_hold: np.ndarray | None = None
    gripper_ctrl: float | None = None


@dataclass
class ControlStats:
    """Counters and operator messages that outlive one scene (a session keeps them across resets)."""

    ik_failures: int = 0  # ticks in which IK could not reach the target
    clamped: int = 0  # targets pulled back into the reachable workspace
    ignored_commands: int = 0  # commands for no arm, or with non-finite numbers
    messages: list[str] = field(default_factory=list)

    def note(self, message: str) -> None:
        """Remember a message for the operator (deduplicated, most recent last)."""
        if not self.messages or self.messages[-1] != message:
            self.messages.append(message)
            del self.messages[:-20]


@dataclass
class StepResult:
    """What happened in one control tick."""

    time: float  # s, sim time after the tick
    ik_ok: bool
    tracking_error_m: np.ndarray  # per arm, target vs actual EE position after the step
    events: tuple[str, ...] = ()


class TickObserver(Protocol):
    """Something that watches ticks (the recorder): it may read, never write, the MjData."""

    def before_ctrl(self, controller: "Controller") -> None:
        """Called after commands are applied, before ctrl is written: the state replay restores."""
        ...

    def after_physics(self, controller: "Controller", commands: Sequence[Command]) -> None:
        """Called after the physics steps of the tick."""
        ...


class Controller:
    """Commands in, physics out, for one compiled scene at a fixed control rate."""

    def __init__(self, scene: Scene, control_hz: float, stats: ControlStats | None = None) -> None:
        self.scene = scene
        self.stats = stats if stats is not None else ControlStats()
        self.control_hz = float(control_hz)
        self.dt = 1.0 / self.control_hz  # s per control tick
        self.substeps, self.timestep = physics_split(self.control_hz)
        self.model = scene.model
        self.data = scene.make_data()
        self.arms: list[ArmState] = []
        for arm in scene.arms:
            ik = ArmIK(scene.xml, scene.assets, arm, self.dt)
            ctrl_ids = np.array([actuator_for_joint(self.model, j) for j in arm.joints])
            if None in list(ctrl_ids):
                raise ValueError(f"an arm joint of {arm.ee_site} has no actuator")
            gripper_id = self.model.actuator(arm.gripper.actuator).id if arm.gripper else None
            ctrl_ids = ctrl_ids.astype(int)
            runs = len(ctrl_ids) > 0 and np.array_equal(ctrl_ids, np.arange(ctrl_ids[0], ctrl_ids[0] + len(ctrl_ids)))
            index = slice(int(ctrl_ids[0]), int(ctrl_ids[0]) + len(ctrl_ids)) if runs else ctrl_ids
            jids = [self.model.joint(j).id for j in arm.joints]
            limited = self.model.jnt_limited[jids].astype(bool)
            ranges = self.model.jnt_range[jids]
            state = ArmState(ik=ik, site_id=self.model.site(arm.ee_site).id, ctrl_ids=ctrl_ids, gripper_id=gripper_id,
                             ctrl_index=index, qpos_ids=self.model.jnt_qposadr[jids].astype(int),
                             joint_lo=np.where(limited, ranges[:, 0], -np.inf), joint_hi=np.where(limited, ranges[:, 1], np.inf))
            state.target_pos, state.target_quat = ik.ee_pose()
            self.arms.append(state)
        self.base_pos = [
            self.data.xpos[self.model.jnt_bodyid[self.model.joint(a.joints[0]).id]].copy() for a in scene.arms
        ]
        self.reach = scene.robot.reach
        self._base_xyz = [tuple(float(v) for v in b) for b in self.base_pos]
        self._inside_reach2 = (self.reach * (1.0 - 1e-9)) ** 2  # m^2, clear of the reach test's rounding
        self.nstate = mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_INTEGRATION)
        self.steps = 0
        self._judged: tuple[int, float, bool] | None = None  # (steps, sim time, success) the step judged
        self._observe = scene.observer(self.data)  # a task with a `hold`: judged and timed every tick; else None
        # Per-tick errors for summaries; bounded so a long browser session does not grow without end.
        self.tracking_errors: deque[np.ndarray] = deque(maxlen=TRACKING_HISTORY)

    # --- what a device may look at (devices.view.SessionView) ---------------

    @property
    def time(self) -> float:
        return float(self.data.time)

    @property
    def n_arms(self) -> int:
        return len(self.arms)

    def ee_pose(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Actual EE (position m, wxyz quaternion), world frame."""
        a = self.arms[arm]
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[a.site_id])
        return self.data.site_xpos[a.site_id].copy(), quat

    def target_pose(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """EE target (position m, wxyz quaternion), world frame."""
        a = self.arms[arm]
        return a.target_pos.copy(), a.target_quat.copy()

    def body_pos(self, name: str) -> np.ndarray:
        bid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            raise KeyError(f"no body named {name!r} in the scene")
        return self.data.xpos[bid].copy()

    def body_quat(self, name: str) -> np.ndarray:
        """World orientation (wxyz quaternion) of a body; KeyError naming it if unknown."""
        bid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            raise KeyError(f"no body named {name!r} in the scene")
        return self.data.xquat[bid].copy()

    @property
    def robot_name(self) -> str:
        """The robot's name (`teleop robots`)."""
        return self.scene.robot.name

    def joint_names(self, arm: int = 0) -> tuple[str, ...]:
        """The arm's joints in the robot's own order, named as in the robot's model (no mount prefix)."""
        names = self.scene.arms[arm].joints
        mounts = self.scene.robot.mounts
        prefix = mounts[arm].prefix if arm < len(mounts) else ""
        return tuple(n[len(prefix):] if prefix and n.startswith(prefix) else n for n in names)

    def joint_positions(self, arm: int = 0) -> np.ndarray:
        """The arm's joint positions now (rad, `joint_names` order)."""
        return self.data.qpos[self.arms[arm].qpos_ids].copy()

    def joint_targets(self, arm: int = 0) -> np.ndarray:
        """The arm's joint position targets now: its actuators' ctrl (rad, `joint_names` order)."""
        return self.data.ctrl[self.arms[arm].ctrl_ids].copy()

    def joint_limits(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of each arm joint's range (rad; +-inf for an unlimited joint)."""
        a = self.arms[arm]
        return a.joint_lo.copy(), a.joint_hi.copy()

    def base_pose(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """World (position m, wxyz quaternion) of the arm's base: the body its first joint's link hangs from."""
        first = self.model.joint(self.scene.arms[arm].joints[0]).id
        bid = int(self.model.body_parentid[self.model.jnt_bodyid[first]])
        return self.data.xpos[bid].copy(), self.data.xquat[bid].copy()

    def success(self) -> bool:
        """The task's success predicate now; judged once a tick (a task with a `hold` is judged by the step)."""
        judged = self._judged
        if judged is not None and judged[0] == self.steps and judged[1] == self.data.time:
            return judged[2]
        ok = bool(self.scene.success(self.data))
        self._judged = (self.steps, self.data.time, ok)
        return ok

    # --- commands ------------------------------------------------------------

    def note(self, message: str) -> None:
        self.stats.note(message)

    def clamp_target(self, arm: int, pos: np.ndarray) -> np.ndarray:
        """Keep a target inside what the arm can reach and above the table."""
        # Well inside both limits (the usual tick): the target as it is, found in plain floats. The margin
        # keeps the reach test clear of rounding, so the answer is the one the exact test below gives.
        x, y, z = pos.tolist()
        bx, by, bz = self._base_xyz[arm]
        if TABLE_TOP + 0.005 <= z <= bz + self.reach:
            dx, dy, dz = x - bx, y - by, z - bz
            if dx * dx + dy * dy + dz * dz < self._inside_reach2:
                return pos.copy()
        base = self.base_pos[arm]
        out = pos.copy()
        z = float(out[2])
        out[2] = min(max(z, TABLE_TOP + 0.005), base[2] + self.reach)
        changed = out[2] != z
        offset = out - base
        dist = norm(offset)
        if dist > self.reach:
            out = base + offset * (self.reach / dist)
            changed = True
        # np.allclose(out, pos) (finite numbers), only when something was moved: it runs every tick
        if changed and not (np.abs(out - pos) <= 1e-8 + 1e-5 * np.abs(pos)).all():
            self.stats.clamped += 1
        return out

    def apply(self, command: Command) -> None:
        """Fold one device command into its arm's target and gripper."""
        if not 0 <= command.arm < len(self.arms):
            self.stats.ignored_commands += 1
            return
        arm = self.arms[command.arm]
        if command.joints is not None or command.gripper_opening is not None:
            self._apply_joints(command, arm)
            return
        # Read, never written in place below: every step makes a new array.
        pos = arm.target_pos if command.target_pos is None else np.asarray(command.target_pos, dtype=float)
        quat = arm.target_quat if command.target_quat is None else np.asarray(command.target_quat, dtype=float)
        translation = np.asarray(command.translation, dtype=float)
        rotation = np.asarray(command.rotation, dtype=float)
        # An absolute target (no translation or rotation: a gizmo, a script, a policy) skips the
        # composition; adding zeros and multiplying by the identity quaternion change no bit.
        if any(translation.tolist()):  # nonzero, or NaN (truthy): a list's any() beats numpy's on 3 values
            if command.frame == "ee":
                rot = np.empty(9)
                mujoco.mju_quat2Mat(rot, quat)
                translation = rot.reshape(3, 3) @ translation
            pos = pos + translation
        if any(rotation.tolist()):
            if command.frame == "ee":
                quat = quat_mul(quat, axis_angle_quat(rotation))
            else:
                quat = quat_mul(axis_angle_quat(rotation), quat)
        size = norm(quat)
        # finite and not absurd: a dot product is NaN or inf when any entry is (0.3 us against 1 us for np.isfinite().all())
        if not (math.isfinite(pos.dot(pos)) and math.isfinite(size) and size > 0):
            self.stats.ignored_commands += 1
            self.note(f"ignored a non-finite target from {command.source or 'a device'}")
            return
        if arm.joint_hold is not None and (
            command.target_pos is not None or command.target_quat is not None or any(translation.tolist()) or any(rotation.tolist())
        ):
            arm.joint_hold = None  # an EE command: IK drives again, from the held joints (IK was reset to them)
        arm.target_pos = self.clamp_target(command.arm, pos)
        arm.target_quat = quat / size
        if command.gripper is not None:  # most ticks carry none
            self._apply_gripper(command, arm)

    @staticmethod
    def _apply_gripper(command: Command, arm: ArmState) -> None:
        if command.gripper is None:
            return
        arm.gripper_ctrl = None
        if command.gripper == "open":
            arm.gripper_open = True
        elif command.gripper == "close":
            arm.gripper_open = False
        elif command.gripper == "toggle":
            arm.gripper_open = not arm.gripper_open

    def _apply_joints(self, command: Command, arm: ArmState) -> None:
        """A joint command (a leader arm): hold its joint targets, clamped to the ranges, with IK and the
        EE target moved to them (forward kinematics), so a later EE command starts where the arm is."""
        q = None
        if command.joints is not None:
            try:
                q = np.array(command.joints, dtype=float)
            except (TypeError, ValueError):
                q = None
            if q is None or q.shape != arm.joint_lo.shape or not math.isfinite(q.dot(q)):
                self.stats.ignored_commands += 1
                n = len(arm.qpos_ids)
                self.note(f"ignored joint targets from {command.source or 'a device'}: need {n} finite numbers (rad)")
                return
        opening = command.gripper_opening
        if opening is not None:
            opening = number_or_nan(opening)
            if not math.isfinite(opening):
                self.stats.ignored_commands += 1
                self.note(f"ignored a non-finite gripper opening from {command.source or 'a device'}")
                return
        if q is not None:
            held = np.minimum(np.maximum(q, arm.joint_lo), arm.joint_hi)
            if held.tolist() != q.tolist():
                self.stats.clamped += 1
            arm.joint_hold = held
            arm.ik.reset(held)
            arm.target_pos, arm.target_quat = arm.ik.ee_pose()
        if opening is not None and arm.gripper_id is not None:
            g = arm.ik.arm.gripper
            opening = min(max(opening, 0.0), 1.0)
            arm.gripper_ctrl = g.closed + opening * (g.open - g.closed)
            arm.gripper_open = opening >= 0.5
        self._apply_gripper(command, arm)

    # --- the tick ------------------------------------------------------------

    def follow_ctrl(self) -> None:
        """Point IK and the EE targets at what data.ctrl commands now.

        For ticks driven by joint targets (a policy's joint action) and after a
        restored state: IK then starts from the commanded joints, and the EE
        target is where they put the EE (forward kinematics), so tracking
        errors, recorded EE targets and a switch back to EE commands stay meaningful.
        """
        ctrl = self.data.ctrl
        for arm in self.arms:
            arm.joint_hold = arm.gripper_ctrl = None
            arm.ik.reset(ctrl[arm.ctrl_ids])
            arm.target_pos, arm.target_quat = arm.ik.ee_pose()
            if arm.gripper_id is not None:
                g = arm.ik.arm.gripper
                value = float(ctrl[arm.gripper_id])
                arm.gripper_open = abs(value - g.open) <= abs(value - g.closed)

    def step(
        self, commands: Sequence[Command] = (), observer: TickObserver | None = None, ctrl: np.ndarray | None = None
    ) -> StepResult:
        """One control tick: apply commands, solve IK, step physics `substeps` times.

        Episode events carried by the commands are returned, not acted on: the
        session decides what they mean. `ctrl` (nu values: joint targets and
        gripper ctrl, the recorded layout) drives the tick instead of IK; the
        EE targets then follow it (`follow_ctrl`).
        """
        events: list[str] = []
        for command in commands:
            self.apply(command)
            events.extend(command.events)
        # The observed state is taken before ctrl changes, so that state k+1 is
        # exactly what stepping state k under ctrl k produces.
        if observer is not None:
            observer.before_ctrl(self)
        if ctrl is None:
            ik_ok = self._solve_ik()
        else:
            self.data.ctrl[:] = ctrl
            self.follow_ctrl()
            ik_ok = True
        if not ik_ok:
            self.stats.ik_failures += 1
            self.note("IK failed: holding the last good joint targets")

        data = self.data
        mujoco.mj_step(self.model, data, nstep=self.substeps)
        mujoco.mj_kinematics(self.model, data)  # poses at the new state, for errors and views
        self.steps += 1
        now = data.time  # s of sim time, read once
        observe = self._observe  # a task whose success must hold for a while is timed every tick
        self._judged = None if observe is None else (self.steps, now, observe())

        site_xpos = data.site_xpos
        errors = np.array([mju_dist3(site_xpos[a.site_id], a.target_pos) for a in self.arms])  # m, EE to target
        self.tracking_errors.append(errors)
        if observer is not None:
            observer.after_physics(self, commands)
        return StepResult(time=now, ik_ok=ik_ok, tracking_error_m=errors, events=tuple(events))

    def _solve_ik(self) -> bool:
        """Joint targets for every arm's EE target into data.ctrl; False if IK failed for one."""
        ok = True
        ctrl = self.data.ctrl
        for arm in self.arms:
            if arm.joint_hold is not None:  # a joint command holds the arm: no IK
                ctrl[arm.ctrl_index] = arm.joint_hold
            else:
                if not arm.ik.solve(arm.target_pos, arm.target_quat):
                    ok = False
                ctrl[arm.ctrl_index] = arm.ik.q
            if arm.gripper_id is not None:
                if arm.gripper_ctrl is not None:
                    ctrl[arm.gripper_id] = arm.gripper_ctrl
                else:
                    g = arm.ik.arm.gripper
                    ctrl[arm.gripper_id] = g.open if arm.gripper_open else g.closed
        return ok

    def tracking_error_mm(self, since: int = 0) -> dict[str, float | None]:
        """Median and max distance (mm) from EE target to actual EE over the ticks kept (from index `since`)."""
        kept = list(self.tracking_errors)[since:]
        if not kept:
            return {"median": None, "max": None}
        errors = np.concatenate(kept) * 1000.0
        return {"median": round(float(np.median(errors)), 3), "max": round(float(np.max(errors)), 3)}
