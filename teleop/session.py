"""The control loop: device commands -> EE targets -> IK -> joint targets -> physics.

One `step` is one control tick: commands are applied to each arm's target,
the target is clamped to the reachable workspace, IK turns it into joint
position targets, and physics runs `substeps` steps under that ctrl. Only
ctrl and mj_step touch the physics MjData, which is what makes recordings
replay bit for bit.
"""

from __future__ import annotations

import math
import platform
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import mujoco
import numpy as np

from scenes import RobotSpec, Scene, actuator_for_joint, build_scene, load_robot
from scenes.arena import TABLE_TOP
from teleop.command import Command
from teleop.ik import ArmIK
from teleop.record_row import RowFiller

SCHEMA_VERSION = 1
TRACKING_HISTORY = 200_000  # ticks (about 2 h at 30 Hz)
MAX_PHYSICS_STEP = 0.002  # s; the control period is split into equal steps no longer than this


def physics_split(control_hz: float) -> tuple[int, float]:
    """Substeps per control tick and the physics timestep that makes the rate exact."""
    period = 1.0 / control_hz
    substeps = max(1, math.ceil(period / MAX_PHYSICS_STEP - 1e-9))
    return substeps, period / substeps


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


def axis_angle_quat(rotvec: np.ndarray) -> np.ndarray:
    """wxyz quaternion of an axis-angle vector (radians)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    out = np.empty(4)
    mujoco.mju_axisAngle2Quat(out, np.asarray(rotvec, float) / angle, angle)
    return out


@dataclass
class ArmState:
    """One arm's IK, target and gripper."""

    ik: ArmIK
    site_id: int
    ctrl_ids: np.ndarray  # actuator index per arm joint
    gripper_id: int | None
    target_pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    target_quat: np.ndarray = field(default_factory=lambda: np.array([1.0, 0, 0, 0]))
    gripper_open: bool = True


@dataclass
class StepResult:
    """What happened in one control tick."""

    time: float
    ik_ok: bool
    tracking_error_m: np.ndarray  # per arm, target vs actual after the step
    events: tuple[str, ...] = ()


@dataclass
class RecordOptions:
    directory: Path
    formats: tuple[str, ...] = ("mcap",)
    verify: bool = True


class Session:
    """A robot in a task scene, driven by Commands, optionally recording episodes."""

    def __init__(
        self,
        scene: str = "lift",
        robot: str | Path | RobotSpec = "panda",
        seed: int = 0,
        control_hz: float = 30.0,
        record: RecordOptions | None = None,
    ):
        if not (0 < control_hz <= 1000) or not math.isfinite(control_hz):
            raise ValueError(f"control rate must be between 0 and 1000 Hz, got {control_hz}")
        self.scene_name = scene
        self.robot = robot if isinstance(robot, RobotSpec) else load_robot(robot)
        self.control_hz = float(control_hz)
        self.dt = 1.0 / self.control_hz
        self.substeps, self.timestep = physics_split(self.control_hz)
        self.record = record
        self.writer = None  # the episode being recorded, if any
        self.episodes_saved = 0
        self.episodes_discarded = 0
        self.saved_paths: list[Path] = []
        self.last_verify = None
        self.ik_failures = 0
        self.record_seconds = 0.0  # control-thread time spent recording (state capture, filling the row, commit)
        self.clamped = 0
        self.ignored_commands = 0
        self.messages: list[str] = []
        self.load(seed)

    # --- scene lifecycle -----------------------------------------------------

    def load(self, seed: int) -> None:
        """Build the scene for `seed` (new model: object placement is part of it)."""
        self.seed = int(seed)
        self.scene: Scene = build_scene(self.scene_name, self.robot, self.seed, timestep=self.timestep)
        self.robot = self.scene.robot  # a user's robot gets its reach measured here
        self.model = self.scene.model
        self.data = self.scene.make_data()
        self.arms: list[ArmState] = []
        for arm in self.scene.arms:
            ik = ArmIK(self.scene.xml, self.scene.assets, arm, self.dt)
            ctrl_ids = np.array([actuator_for_joint(self.model, j) for j in arm.joints])
            if None in list(ctrl_ids):
                raise ValueError(f"an arm joint of {arm.ee_site} has no actuator")
            gripper_id = self.model.actuator(arm.gripper.actuator).id if arm.gripper else None
            state = ArmState(ik=ik, site_id=self.model.site(arm.ee_site).id, ctrl_ids=ctrl_ids, gripper_id=gripper_id)
            state.target_pos, state.target_quat = ik.ee_pose()
            self.arms.append(state)
        self.base_pos = [self.data.xpos[self.model.jnt_bodyid[self.model.joint(a.joints[0]).id]].copy() for a in self.scene.arms]
        self.steps = 0
        # Per-tick errors for summaries; bounded so a long browser session does not grow without end.
        self.tracking_errors: deque[np.ndarray] = deque(maxlen=TRACKING_HISTORY)
        self.nstate = mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_INTEGRATION)

    def reset(self, seed: int | None = None) -> None:
        """New episode layout: the next seed unless one is given. Ends a recording first."""
        if self.writer is not None:
            self.save_episode()
        self.load(self.seed + 1 if seed is None else seed)

    # --- SessionView ---------------------------------------------------------

    @property
    def time(self) -> float:
        return float(self.data.time)

    @property
    def n_arms(self) -> int:
        return len(self.arms)

    def ee_pose(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        a = self.arms[arm]
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[a.site_id])
        return self.data.site_xpos[a.site_id].copy(), quat

    def target_pose(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        a = self.arms[arm]
        return a.target_pos.copy(), a.target_quat.copy()

    def body_pos(self, name: str) -> np.ndarray:
        bid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            raise KeyError(f"no body named {name!r} in the scene")
        return self.data.xpos[bid].copy()

    def success(self) -> bool:
        return self.scene.success(self.data)

    # --- commands ------------------------------------------------------------

    def clamp_target(self, arm: int, pos: np.ndarray) -> np.ndarray:
        """Keep a target inside what the arm can reach and above the table."""
        base = self.base_pos[arm]
        reach = self.robot.reach
        out = pos.copy()
        out[2] = min(max(out[2], TABLE_TOP + 0.005), base[2] + reach)
        offset = out - base
        dist = float(np.linalg.norm(offset))
        if dist > reach:
            out = base + offset * (reach / dist)
        if not np.allclose(out, pos):
            self.clamped += 1
        return out

    def apply(self, command: Command) -> None:
        """Fold one device command into its arm's target and gripper."""
        if not 0 <= command.arm < len(self.arms):
            self.ignored_commands += 1
            return
        arm = self.arms[command.arm]
        pos, quat = arm.target_pos.copy(), arm.target_quat.copy()
        if command.target_pos is not None:
            pos = np.asarray(command.target_pos, dtype=float)
        if command.target_quat is not None:
            quat = np.asarray(command.target_quat, dtype=float)
        translation = np.asarray(command.translation, dtype=float)
        rotation = np.asarray(command.rotation, dtype=float)
        if command.frame == "ee":
            rot = np.empty(9)
            mujoco.mju_quat2Mat(rot, quat)
            translation = rot.reshape(3, 3) @ translation
            quat = quat_mul(quat, axis_angle_quat(rotation))
        else:
            quat = quat_mul(axis_angle_quat(rotation), quat)
        pos = pos + translation
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat)) and np.linalg.norm(quat) > 0):
            self.ignored_commands += 1
            self.note(f"ignored a non-finite target from {command.source or 'a device'}")
            return
        arm.target_pos = self.clamp_target(command.arm, pos)
        arm.target_quat = quat / np.linalg.norm(quat)
        if command.gripper == "open":
            arm.gripper_open = True
        elif command.gripper == "close":
            arm.gripper_open = False
        elif command.gripper == "toggle":
            arm.gripper_open = not arm.gripper_open

    def note(self, message: str) -> None:
        """Remember a message for the operator (deduplicated, most recent last)."""
        if not self.messages or self.messages[-1] != message:
            self.messages.append(message)
            del self.messages[:-20]

    # --- the tick ------------------------------------------------------------

    def step(self, commands: list[Command] = ()) -> StepResult:
        """One control tick: apply commands, solve IK, step physics `substeps` times."""
        events: list[str] = []
        for command in commands:
            self.apply(command)
            events.extend(command.events)
        for event in events:
            self.handle_event(event)

        # The recorded state is taken before ctrl changes, so that state k+1 is
        # exactly what stepping state k under ctrl k produces. It goes straight into
        # the recorder's next row; the rest of the row is filled after the step.
        writer = self.writer
        if writer is not None:
            t_rec = time.perf_counter()
            row = writer.claim()
            self._row_filler.capture_state(row, self.data)
            self.record_seconds += time.perf_counter() - t_rec

        ik_ok = True
        ctrl = self.data.ctrl
        for arm in self.arms:
            if not arm.ik.solve(arm.target_pos, arm.target_quat):
                ik_ok = False
            ctrl[arm.ctrl_ids] = arm.ik.q
            if arm.gripper_id is not None:
                g = arm.ik.arm.gripper
                ctrl[arm.gripper_id] = g.open if arm.gripper_open else g.closed
        if not ik_ok:
            self.ik_failures += 1
            self.note("IK failed: holding the last good joint targets")

        mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        mujoco.mj_kinematics(self.model, self.data)  # poses at the new state, for errors and views

        errors = np.array([np.linalg.norm(self.data.site_xpos[a.site_id] - a.target_pos) for a in self.arms])
        self.tracking_errors.append(errors)
        self.steps += 1
        if writer is not None:
            t_rec = time.perf_counter()
            self._row_filler.finish(row, self.data, self.arms)
            writer.commit(commands)  # Command objects: the writer thread turns them into dicts
            self.record_seconds += time.perf_counter() - t_rec
        return StepResult(time=self.time, ik_ok=ik_ok, tracking_error_m=errors, events=tuple(events))

    # --- recording -----------------------------------------------------------

    def handle_event(self, event: str) -> None:
        if event == "start":
            self.start_episode()
        elif event == "save":
            self.save_episode()
        elif event == "discard":
            self.discard_episode()
        elif event == "reset":
            self.reset()

    @property
    def recording(self) -> bool:
        return self.writer is not None

    def metadata(self, index: int) -> dict:
        from importlib.metadata import version

        return {
            "schema_version": SCHEMA_VERSION,
            "scene": self.scene_name,
            "robot": self.robot.name,
            "robot_spec": {
                "name": self.robot.name,
                "arms": [
                    {
                        "ee_site": a.ee_site,
                        "joints": list(a.joints),
                        "actuators": [self.model.actuator(i).name for i in arm.ctrl_ids],
                        "gripper_actuator": a.gripper.actuator if a.gripper else None,
                        "gripper_open": a.gripper.open if a.gripper else None,
                        "gripper_closed": a.gripper.closed if a.gripper else None,
                        "home": list(a.home),
                    }
                    for a, arm in zip(self.scene.arms, self.arms)
                ],
            },
            "model_xml": self.scene.xml,
            "assets": dict(self.scene.assets),
            "mujoco_version": mujoco.__version__,
            "teleop_version": version("mujoco-teleop") if _installed("mujoco-teleop") else "dev",
            "platform": platform.platform(),
            "machine": platform.machine(),
            "python_version": sys.version.split()[0],
            "seed": self.seed,
            "control_hz": self.control_hz,
            "timestep": self.timestep,
            "substeps": self.substeps,
            "task": self.scene.task.text,
            "cameras": list(self.scene.cameras),
            "nstate": self.nstate,
            "nq": self.model.nq,
            "nv": self.model.nv,
            "nu": self.model.nu,
            "start_time": datetime.now(timezone.utc).isoformat(),
            "episode_index": index,
        }

    def start_episode(self) -> None:
        """Begin recording from the current state (no-op without a record directory)."""
        if self.record is None:
            self.note("not recording: start the session with --record DIR")
            return
        if self.writer is not None:
            return
        from recorder import EpisodeWriter, next_episode_index

        self.record.directory.mkdir(parents=True, exist_ok=True)
        index = next_episode_index(self.record.directory)
        self.writer = EpisodeWriter(self.record.directory, index, self.record.formats, self.metadata(index))
        self._row_filler = RowFiller(self.writer.columns, self.model, len(self.arms))
        self.tracking_errors.clear()
        self.steps = 0

    def save_episode(self, complete: bool = True) -> list[Path]:
        """Finish the episode in progress; returns its files."""
        writer, self.writer = self.writer, None
        if writer is None:
            return []
        paths = writer.close(success=self.success(), complete=complete)
        self.episodes_saved += 1
        self.saved_paths.extend(paths)
        if self.record is not None and self.record.verify and complete and paths:
            from replay import verify_file

            self.last_verify = verify_file(paths[0])
            if not self.last_verify.bit_exact:
                self.note(f"episode {paths[0].name} did not replay exactly (step {self.last_verify.first_divergence_step})")
        return paths

    def discard_episode(self) -> None:
        writer, self.writer = self.writer, None
        if writer is not None:
            writer.discard()
            self.episodes_discarded += 1

    def close(self) -> None:
        """End the session; an episode in progress is kept, marked incomplete."""
        if self.writer is not None:
            self.save_episode(complete=False)

    # --- summaries -----------------------------------------------------------

    def tracking_error_mm(self) -> dict[str, float | None]:
        if not self.tracking_errors:
            return {"median": None, "max": None}
        errors = np.concatenate(self.tracking_errors) * 1000.0
        return {"median": round(float(np.median(errors)), 3), "max": round(float(np.max(errors)), 3)}


def _installed(name: str) -> bool:
    from importlib.metadata import PackageNotFoundError, version

    try:
        version(name)
        return True
    except PackageNotFoundError:
        return False
