"""Scripted device: a JSON list of timed moves, for tests, demos and automation.

    {"steps": [
      {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.1], "gripper": "open"},
      {"duration": 0.8, "move": [0, 0, -0.1]},
      {"duration": 0.5, "gripper": "close"},
      {"duration": 1.0, "move": [0, 0, 0.15]}
    ]}

Each step moves the arm's target from where it is at the step's start to the
step's goal, linearly over `duration` seconds (no jumps), and rotates it by
`rotate` (axis-angle, world frame). Goals resolve when the step begins, so
`to_body` aims at where the body is then.
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

STEP_KEYS = {"duration", "move", "rotate", "to", "to_body", "offset", "gripper", "arm"}


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
        if step.rotate is not None:
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
