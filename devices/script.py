"""Scripted device: a JSON list of timed moves, for tests, demos and automation.

    {"steps": [
      {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.1], "gripper": "open"},
      {"duration": 0.8, "move": [0, 0, -0.1]},
      {"duration": 0.5, "gripper": "close"},
      {"duration": 1.0, "move": [0, 0, 0.15]}
    ]}

Each step moves the arm's target from where it is at the step's start to the
step's goal, linearly over `duration` seconds (no jumps), and rotates it by
`rotate` (axis-angle, world frame) or to `orient` (an absolute hand orientation:
[roll, pitch, yaw] in radians about the workspace's fixed x, y, z axes, which are
the world's; every built-in robot's hand starts at [pi, 0, 0], pointing down).
`"align": "yaw"` with `to_body` turns the hand about the vertical to the body's
yaw, taking the nearer of a parallel gripper's two grasps (the yaw mod pi), so an
object placed at any yaw is grasped across the same side. Goals resolve when the
step begins, so `to_body` aims at where the body is then.

Every name a script uses (bodies, arms) is checked against the scene by `check`
before the first tick (the episode loop calls it), so a misspelt step 5 stops the
run before anything is recorded.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from devices.base import DeviceError
from devices.command import Command
from devices.view import SessionView
from scenes.errors import TeleopError

STEP_KEYS = {"duration", "move", "rotate", "orient", "to", "to_body", "offset", "align", "gripper", "arm"}
ALIGN = ("yaw",)  # what `align` may turn the hand to


class ScriptError(TeleopError, ValueError):
    """A malformed script; the message names the file, step and field."""


@dataclass(frozen=True)
class ScriptStep:
    duration: float
    move: np.ndarray | None = None
    rotate: np.ndarray | None = None
    to: np.ndarray | None = None
    to_body: str | None = None
    offset: np.ndarray | None = None
    gripper: str | None = None
    arm: int = 0
    orient: np.ndarray | None = None  # absolute [roll, pitch, yaw] (rad) about the workspace's axes
    align: str | None = None  # "yaw": turn the hand to the `to_body` body's yaw (mod pi)


def _vector(where: str, key: str, value) -> np.ndarray:
    if (
        not isinstance(value, list)
        or len(value) != 3
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    ):
        raise ScriptError(f"{where}: '{key}' must be a list of 3 finite numbers")
    return np.array(value, dtype=float)


def parse_script(text: str, name: str = "script") -> list[ScriptStep]:
    """Validate and parse a script; raises ScriptError naming the step and field at fault."""
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ScriptError(f"{name}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("steps"), list):
        raise ScriptError(f'{name}: expected an object with a "steps" list')
    if not raw["steps"]:
        raise ScriptError(f"{name}: 'steps' is empty")
    steps = []
    for i, step in enumerate(raw["steps"], start=1):
        where = f"{name}: step {i}"
        if not isinstance(step, dict):
            raise ScriptError(f"{where}: must be an object")
        unknown = set(step) - STEP_KEYS
        if unknown:
            raise ScriptError(f"{where}: unknown field '{sorted(unknown)[0]}' (fields: {', '.join(sorted(STEP_KEYS))})")
        duration = step.get("duration")
        if not isinstance(duration, (int, float)) or isinstance(duration, bool) or not (0 < duration < 1e6):
            raise ScriptError(f"{where}: 'duration' must be a positive number of seconds")
        targets = [k for k in ("move", "to", "to_body") if k in step]
        if len(targets) > 1:
            raise ScriptError(f"{where}: '{targets[1]}' cannot be combined with '{targets[0]}'")
        if "offset" in step and "to_body" not in step:
            raise ScriptError(f"{where}: 'offset' needs 'to_body'")
        align = step.get("align")
        if align is not None and align not in ALIGN:
            raise ScriptError(f"{where}: 'align' must be \"yaw\"")
        if align is not None and "to_body" not in step:
            raise ScriptError(f"{where}: 'align' needs 'to_body'")
        turns = [k for k in ("rotate", "orient", "align") if k in step]
        if len(turns) > 1:
            raise ScriptError(f"{where}: '{turns[1]}' cannot be combined with '{turns[0]}'")
        to_body = step.get("to_body")
        if to_body is not None and (not isinstance(to_body, str) or not to_body):
            raise ScriptError(f"{where}: 'to_body' must be a body name")
        gripper = step.get("gripper")
        if gripper is not None and gripper not in ("open", "close"):
            raise ScriptError(f"{where}: 'gripper' must be \"open\" or \"close\"")
        arm = step.get("arm", 0)
        if not isinstance(arm, int) or isinstance(arm, bool) or arm < 0:
            raise ScriptError(f"{where}: 'arm' must be a non-negative integer")
        steps.append(
            ScriptStep(
                duration=float(duration),
                move=_vector(where, "move", step["move"]) if "move" in step else None,
                rotate=_vector(where, "rotate", step["rotate"]) if "rotate" in step else None,
                to=_vector(where, "to", step["to"]) if "to" in step else None,
                to_body=to_body,
                offset=_vector(where, "offset", step["offset"]) if "offset" in step else None,
                gripper=gripper,
                arm=arm,
                orient=_vector(where, "orient", step["orient"]) if "orient" in step else None,
                align=align,
            )
        )
    return steps


def load_script(path: str | Path) -> list[ScriptStep]:
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ScriptError(f"{path}: no such script file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScriptError(f"{path}: cannot read script ({exc.__class__.__name__})") from None
    return parse_script(text, str(path))


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical interpolation of wxyz quaternions."""
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    return (math.sin((1 - s) * theta) * q0 + math.sin(s * theta) * q1) / math.sin(theta)


def rpy_quat(rpy: np.ndarray) -> np.ndarray:
    """wxyz quaternion of [roll, pitch, yaw] (rad) about the fixed x, y, z axes: Rz(yaw) Ry(pitch) Rx(roll)."""
    out = np.array([1.0, 0.0, 0.0, 0.0])
    for axis, angle in zip(np.eye(3), rpy):
        turn = np.empty(4)
        mujoco.mju_axisAngle2Quat(turn, axis, float(angle))
        mujoco.mju_mulQuat(out, turn, out.copy())
    return out


def heading(quat: np.ndarray) -> float:
    """Yaw (rad) of a frame's x axis about the vertical: a body's yaw, or a hand's pointing down."""
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, quat)
    return math.atan2(mat[3], mat[0])


def turned_to_yaw(hand: np.ndarray, yaw: float, symmetry: float = math.pi) -> np.ndarray:
    """`hand` turned about the vertical to `yaw`, or to the nearest of yaw + k * symmetry (rad): the
    least turn that lines a gripper symmetric under `symmetry` up with it."""
    turn = (yaw - heading(hand) + symmetry / 2) % symmetry - symmetry / 2
    rot, out = np.empty(4), np.empty(4)
    mujoco.mju_axisAngle2Quat(rot, np.array([0.0, 0.0, 1.0]), turn)
    mujoco.mju_mulQuat(out, rot, hand)
    return out


class ScriptDevice:
    """Plays a script: absolute targets each tick, interpolated from each step's start."""

    kind = "script"

    def __init__(self, path: str | Path):
        """Read and check the script now: a malformed one raises ScriptError naming the step and field."""
        self.path = Path(path)
        self.name = f"script:{self.path.name}"
        self.steps: list[ScriptStep] = load_script(self.path)
        self.index = 0
        self.elapsed = 0.0
        self._start: tuple[np.ndarray, np.ndarray] | None = None
        self._goal: tuple[np.ndarray, np.ndarray] | None = None

    def start(self) -> None:
        """Play from the first step."""
        self.restart()

    def restart(self) -> None:
        """Play again from the first step (one run per recorded episode)."""
        self.index = 0
        self.elapsed = 0.0
        self._start = self._goal = None

    @property
    def finished(self) -> bool:
        return self.index >= len(self.steps)

    def status(self) -> str:
        return "done" if self.finished else f"step {self.index + 1}/{len(self.steps)}"

    def duration(self) -> float:
        return sum(s.duration for s in self.steps)

    def check(self, view: SessionView) -> None:
        """Check every step against the scene before the first tick: its arm and the bodies it names.

        Raises ScriptError naming the file, step and field, so a bad step 5 stops the run
        before anything is recorded rather than when step 5 begins.
        """
        for i, step in enumerate(self.steps, start=1):
            where = f"{self.path}: step {i}"
            if step.arm >= view.n_arms:
                raise ScriptError(f"{where}: 'arm' {step.arm} but the robot has {view.n_arms} arm(s)")
            if step.to_body is not None:
                try:
                    view.body_pos(step.to_body)
                except KeyError:
                    raise ScriptError(f"{where}: 'to_body' names no body '{step.to_body}' in the scene") from None

    def _begin(self, step: ScriptStep, view: SessionView) -> None:
        if step.arm >= view.n_arms:
            raise DeviceError(f"{self.path}: step {self.index + 1}: 'arm' {step.arm} but the robot has {view.n_arms} arm(s)")
        pos, quat = view.target_pose(step.arm)
        goal = pos.copy()
        if step.move is not None:
            goal = pos + step.move
        elif step.to is not None:
            goal = step.to.copy()
        elif step.to_body is not None:
            try:
                goal = view.body_pos(step.to_body) + (step.offset if step.offset is not None else 0.0)
            except KeyError:
                raise DeviceError(f"{self.path}: step {self.index + 1}: 'to_body' names no body '{step.to_body}'") from None
        goal_quat = quat.copy()
        if step.orient is not None:
            goal_quat = rpy_quat(step.orient)
        elif step.align == "yaw" and step.to_body is not None:
            goal_quat = turned_to_yaw(quat, heading(view.body_quat(step.to_body)))
        elif step.rotate is not None:
            angle = float(np.linalg.norm(step.rotate))
            if angle > 0:
                rot = np.empty(4)
                mujoco.mju_axisAngle2Quat(rot, step.rotate / angle, angle)
                mujoco.mju_mulQuat(goal_quat, rot, quat)
        self._start = (pos, quat)
        self._goal = (goal, goal_quat)

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        if self.finished:
            return []
        step = self.steps[self.index]
        commands = []
        if self._start is None:
            self._begin(step, view)
            if step.gripper is not None:
                commands.append(Command(gripper=step.gripper, arm=step.arm, source=self.name))
        self.elapsed += dt
        s = min(1.0, self.elapsed / step.duration)
        (p0, q0), (p1, q1) = self._start, self._goal
        commands.append(Command(target_pos=p0 + s * (p1 - p0), target_quat=slerp(q0, q1, s), arm=step.arm, source=self.name))
        if self.elapsed >= step.duration - 1e-9:
            self.index += 1
            self.elapsed = 0.0
            self._start = self._goal = None
        return commands

    def close(self) -> None:
        pass
