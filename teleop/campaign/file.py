"""The campaign file (TOML): what to collect, where, and who may join.

    name = "week1"
    out = "week1_data"            # episodes go to out/<task>/ (relative to the campaign file)
    max_sessions = 4              # concurrent sessions; more operators wait in a queue
    session_minutes = 30          # a session ends after this long (the operator may join again)
    operators = ["ana", "bo"]     # or "open" (default): anyone with the join URL picks a name

    [[task]]
    scene = "lift"                # a built-in or library name, or a task file relative to this file
    episodes = 20                 # successful episodes wanted
    robot = "panda"               # optional, as the other keys below
    vary = "physics"              # --vary words: physics drawn per seed
    control_hz = 30
    format = "mcap"               # mcap, hdf5 or both
    name = "lift"                 # the folder under out/ (default: the task's name)

Any bad field is one line (a UsageError: exit code 2), naming the field.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scenes.errors import TeleopError, first_line
from scenes.tasks.registry import find_task
from scenes.vary.variation import VariationError, parse_vary
from teleop.errors import UsageError

NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")  # campaign and task names: folder-safe
OPERATOR_PATTERN = re.compile(r"[^\W_][\w .'-]{0,63}")  # letters, digits, space . ' - _ ; no markup
FORMATS = ("mcap", "hdf5", "both")
TOP_KEYS = {"name", "out", "max_sessions", "session_minutes", "operators", "task"}
TASK_KEYS = {"scene", "episodes", "robot", "vary", "control_hz", "format", "name"}


@dataclass(frozen=True)
class CampaignTask:
    """One [[task]] entry; `name` is its folder under out/."""

    name: str
    scene: str  # as the session's --scene takes it (a task-file path made absolute)
    episodes: int  # successful episodes wanted
    robot: str = "panda"
    vary: str | None = None
    control_hz: float = 30.0
    format: str = "mcap"
    instruction: str = ""


@dataclass(frozen=True)
class Campaign:
    """A read and checked campaign file."""

    name: str
    out: Path
    tasks: tuple[CampaignTask, ...]
    max_sessions: int = 4
    session_minutes: float = 60.0
    operators: tuple[str, ...] | None = None  # None: open

    @property
    def open(self) -> bool:
        return self.operators is None

    def task(self, name: str) -> CampaignTask:
        return next(t for t in self.tasks if t.name == name)


def check_operator_name(name: Any) -> str:
    """An operator's name, stripped; a ValueError with a one-line reason when it cannot be one."""
    if not isinstance(name, str):
        raise ValueError("the name must be a string")
    name = name.strip()
    if not name:
        raise ValueError("the name is empty")
    if len(name) > 64:
        raise ValueError(f"the name is {len(name)} characters long; at most 64")
    if not OPERATOR_PATTERN.fullmatch(name):
        raise ValueError("a name is letters, digits, spaces and . ' - _ only (no markup)")
    return name


def _fail(where: Path, what: str) -> UsageError:
    return UsageError(f"{where}: {what}")


def _number(raw: dict, key: str, where: Path, kind: type, default: Any, low: float, high: float) -> Any:
    value = raw.get(key, default)
    ok_type = isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is int:
        ok_type = isinstance(value, int) and not isinstance(value, bool)
    if not ok_type or not math.isfinite(value) or not low <= value <= high:
        word = "a whole number" if kind is int else "a number"
        raise _fail(where, f"{key} = {value!r}: expected {word} from {low:g} to {high:g}")
    return kind(value)


def _task(raw: Any, index: int, base: Path, where: Path) -> CampaignTask:
    label = f"task {index + 1}"
    if not isinstance(raw, dict):
        raise _fail(where, f"{label}: expected a [[task]] table")
    unknown = sorted(set(raw) - TASK_KEYS)
    if unknown:
        raise _fail(where, f"{label}: unknown key {unknown[0]!r} (keys: {', '.join(sorted(TASK_KEYS))})")
    scene = raw.get("scene")
    if not isinstance(scene, str) or not scene.strip():
        raise _fail(where, f"{label}: scene is required (a built-in or library name, or a task .toml file)")
    if scene.endswith(".toml"):
        path = (base / scene).resolve()
        if not path.is_file():
            raise _fail(where, f"{label}: scene {scene!r}: no such task file (relative to the campaign file)")
        scene = str(path)
    try:  # the scene must exist: checked now, one line
        found = find_task(scene)
    except TeleopError as exc:
        raise _fail(where, f"{label}: {first_line(exc)}") from None
    if "episodes" not in raw:
        raise _fail(where, f"{label}: episodes is required (successful episodes wanted)")
    episodes = _number(raw, "episodes", where, int, 0, 1, 1_000_000)
    robot = raw.get("robot", "panda")
    if not isinstance(robot, str) or not robot:
        raise _fail(where, f"{label}: robot = {robot!r}: expected a built-in robot name or a PATH.toml")
    if robot.endswith(".toml"):
        robot = str((base / robot).resolve())
    vary = raw.get("vary")
    if vary is not None:
        if not isinstance(vary, str):
            raise _fail(where, f"{label}: vary = {vary!r}: expected a comma list of words")
        try:
            parse_vary(vary, "generation")
        except VariationError as exc:
            raise _fail(where, f"{label}: vary: {first_line(exc)}") from None
    fmt = raw.get("format", "mcap")
    if fmt not in FORMATS:
        raise _fail(where, f"{label}: format = {fmt!r}: expected one of {', '.join(FORMATS)}")
    name = raw.get("name", found.name)
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise _fail(where, f"{label}: name = {name!r}: expected letters, digits, . _ - (a folder name)")
    return CampaignTask(name=name, scene=scene, episodes=episodes, robot=robot, vary=vary,
                       control_hz=_number(raw, "control_hz", where, float, 30.0, 1, 1000), format=fmt,
                       instruction=found.instruction_for(0)[0])


def load_campaign(path: str | Path) -> Campaign:
    """Read and check a campaign file; a UsageError (one line) for any bad field."""
    where = Path(path)
    try:
        raw = tomllib.loads(where.read_text())
    except FileNotFoundError:
        raise UsageError(f"{where}: no such campaign file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"{where}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise _fail(where, f"not valid TOML: {str(exc).splitlines()[0]}") from None
    unknown = sorted(set(raw) - TOP_KEYS)
    if unknown:
        raise _fail(where, f"unknown key {unknown[0]!r} (keys: {', '.join(sorted(TOP_KEYS))})")
    name = raw.get("name")
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise _fail(where, f"name = {name!r}: expected 1-64 letters, digits, . _ - (starting with a letter or digit)")
    out = raw.get("out")
    if not isinstance(out, str) or not out.strip():
        raise _fail(where, "out is required: the folder episodes go to (out/<task>/)")
    out_path = (where.parent / out).resolve()
    if out_path.exists() and not out_path.is_dir():
        raise _fail(where, f"out = {out!r}: exists and is not a folder")
    tasks_raw = raw.get("task")
    if not isinstance(tasks_raw, list) or not tasks_raw:
        raise _fail(where, "at least one [[task]] is required")
    tasks = tuple(_task(t, i, where.parent, where) for i, t in enumerate(tasks_raw))
    names = [t.name for t in tasks]
    twice = next((n for n in names if names.count(n) > 1), None)
    if twice is not None:
        raise _fail(where, f"two tasks are named {twice!r}: give one a name = \"...\" of its own")
    operators_raw = raw.get("operators", "open")
    operators: tuple[str, ...] | None
    if operators_raw == "open":
        operators = None
    elif isinstance(operators_raw, list) and operators_raw:
        try:
            operators = tuple(check_operator_name(o) for o in operators_raw)
        except ValueError as exc:
            raise _fail(where, f"operators: {exc}") from None
        if len(set(operators)) != len(operators):
            raise _fail(where, "operators: a name is listed twice")
    else:
        raise _fail(where, f"operators = {operators_raw!r}: expected \"open\" or a list of names")
    return Campaign(name=name, out=out_path, tasks=tasks,
                    max_sessions=_number(raw, "max_sessions", where, int, 4, 1, 256),
                    session_minutes=_number(raw, "session_minutes", where, float, 60.0, 0.1, 24 * 60),
                    operators=operators)
