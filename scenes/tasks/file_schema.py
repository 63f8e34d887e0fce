"""The fields of a task file and their checks at load: tables, names, shapes and plain values.

Lengths are checked for form here but resolved later (they depend on the robot's layout);
every refusal is one line naming the file, the table and the field (TaskFileError).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scenes.tasks.base import SUBTASK_KINDS, SubtaskSpec
from scenes.tasks.file_values import TaskFileError, numbers, positive_lengths, required_str

NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
TASK_NAME = re.compile(r"^[a-z0-9_]+$")
SHAPES = ("box", "cylinder", "sphere", "capsule", "bin", "mesh", "mjcf")
SIZES = {"box": 3, "cylinder": 2, "capsule": 2, "sphere": 1, "bin": 3}  # how many lengths each primitive's size takes
TOP_FIELDS = {"name", "instruction", "instructions", "family", "summary", "robots", "scale", "gap", "success", "hold", "script",
              "subtasks", "constraint", "object", "region", "camera", "variation"}
OBJECT_FIELDS = {"name", *SHAPES, "scale", "wall", "rgba", "mass", "density", "friction", "fixed", "collide", "region", "on", "euler",
                 "z", "min_distance", "joints"}
REGION_FIELDS = {"name", "x", "y", "rgba"}
PLACE_FIELDS = {"x", "y", "yaw"}
CAMERA_FIELDS = {"name", "pos", "look_at", "xyaxes", "quat", "fovy"}

FileFn = Callable[[Any, str, tuple[str, ...]], Path]  # (name as written, where, suffixes) -> the file, recorded for the bundle


@dataclass
class ObjectDef:
    """One `[[object]]` entry as written (lengths still unresolved: they depend on the robot's layout)."""

    name: str
    shape: str
    raw: dict[str, Any]
    file: Path | None = None
    where: str = ""


def named_table(entry: Any, i: int, kind: str, fields: set[str], where: str) -> tuple[str, str]:
    """(where, name) of the i-th [[kind]] table, refused when it is no table, has no name or an unknown field."""
    w = f"{where}: [[{kind}]] {i}"
    if not isinstance(entry, dict):
        raise TaskFileError(f"{w}: expected a table")
    name = required_str(entry, "name", w)
    w = f"{where}: [[{kind}]] '{name}'"
    unknown = sorted(set(entry) - fields)
    if unknown:
        raise TaskFileError(f"{w}: unknown field '{unknown[0]}' (fields: {', '.join(sorted(fields))})")
    return w, name


def read_regions(entries: Any, where: str) -> dict[str, dict]:
    """The `[[region]]` tables by name."""
    out: dict[str, dict] = {}
    if not isinstance(entries, list):
        raise TaskFileError(f"{where}: region: use [[region]] tables")
    for i, entry in enumerate(entries):
        w, name = named_table(entry, i, "region", REGION_FIELDS, where)
        if not NAME.match(name) or name in out:
            raise TaskFileError(f"{w}: name must be a unique identifier")
        for key in ("x", "y"):
            if key not in entry:
                raise TaskFileError(f"{w}: {key}: missing")
        if "rgba" in entry:
            numbers(entry["rgba"], 4, f"{w}: rgba")
        out[name] = entry
    return out


def read_objects(entries: Any, where: str, regions: dict[str, dict], file: FileFn) -> list[ObjectDef]:
    """The `[[object]]` tables in file order; `file` finds (and records) a mesh or mjcf file."""
    if not isinstance(entries, list) or not entries:
        raise TaskFileError(f"{where}: object: a task needs at least one [[object]]")
    out: list[ObjectDef] = []
    seen: set[str] = set()
    for i, entry in enumerate(entries):
        w, name = named_table(entry, i, "object", OBJECT_FIELDS, where)
        if not NAME.match(name) or name in seen or name in regions:
            raise TaskFileError(f"{w}: name: must be an identifier not used by another object or region")
        seen.add(name)
        shapes = [s for s in SHAPES if s in entry]
        if len(shapes) != 1:
            raise TaskFileError(f"{w}: give exactly one of {', '.join(SHAPES)}")
        shape = shapes[0]
        obj = ObjectDef(name, shape, entry, where=w)
        if shape == "mesh":
            obj.file = file(entry["mesh"], f"{w}: mesh", (".obj", ".stl"))
        elif shape == "mjcf":
            obj.file = file(entry["mjcf"], f"{w}: mjcf", (".xml",))
        if "scale" in entry and shape != "mesh":
            raise TaskFileError(f"{w}: scale: only a mesh object has a scale")
        if shape in SIZES:
            positive_lengths(entry[shape], SIZES[shape], f"{w}: {shape}")
        if "scale" in entry and min(numbers(entry["scale"], (1, 3), f"{w}: scale")) <= 0:
            raise TaskFileError(f"{w}: scale: every factor must be > 0 (a negative one mirrors the mesh), got {entry['scale']!r}")
        if "joints" in entry and shape != "mjcf":
            raise TaskFileError(f"{w}: joints: only an mjcf object has joints")
        if "wall" in entry and shape != "bin":
            raise TaskFileError(f"{w}: wall: only a bin has a wall")
        if "wall" in entry:
            positive_lengths(entry["wall"], 1, f"{w}: wall")
        if "mass" in entry and "density" in entry:
            raise TaskFileError(f"{w}: mass: give mass or density, not both")
        for key in ("mass", "density"):
            if key in entry and numbers(entry[key], 1, f"{w}: {key}")[0] <= 0:
                raise TaskFileError(f"{w}: {key}: must be > 0")
        if "rgba" in entry:
            numbers(entry["rgba"], 4, f"{w}: rgba")
        if "friction" in entry:
            numbers(entry["friction"], (1, 3), f"{w}: friction")
        if "euler" in entry:
            numbers(entry["euler"], 3, f"{w}: euler")
        for key in ("fixed", "collide"):
            if key in entry and not isinstance(entry[key], bool):
                raise TaskFileError(f"{w}: {key}: expected true or false")
        if "on" in entry and entry["on"] not in seen - {name}:
            raise TaskFileError(f"{w}: on: {entry['on']!r} is not an object named earlier in the file")
        check_region(entry.get("region"), regions, w)
        if "joints" in entry and not (isinstance(entry["joints"], dict)
                                      and all(isinstance(v, (int, float)) for v in entry["joints"].values())):
            raise TaskFileError(f"{w}: joints: expected {{joint_name = value}}")
        out.append(obj)
    return out


def check_region(region: Any, regions: dict[str, dict], w: str) -> None:
    """An object's `region`: a [[region]] name, a list of them, or an inline {x, y, yaw} box."""
    if isinstance(region, str):
        if region not in regions:
            raise TaskFileError(f"{w}: region: no [[region]] named {region!r}")
    elif isinstance(region, dict):
        unknown = sorted(set(region) - PLACE_FIELDS)
        if unknown:
            raise TaskFileError(f"{w}: region: unknown field '{unknown[0]}' (fields: x, y, yaw)")
    elif isinstance(region, list):
        if not region or not all(isinstance(r, str) and r in regions for r in region):
            raise TaskFileError(f"{w}: region: a list must name [[region]]s")
    elif region is not None:
        raise TaskFileError(f"{w}: region: expected {{x = [lo, hi], y = [lo, hi], yaw = [lo, hi]}} or a region name")


def read_cameras(entries: Any, where: str) -> list[dict]:
    """The `[[camera]]` tables, each with a position and one way to aim it."""
    if not isinstance(entries, list):
        raise TaskFileError(f"{where}: camera: use [[camera]] tables")
    out = []
    for i, entry in enumerate(entries):
        w, name = named_table(entry, i, "camera", CAMERA_FIELDS, where)
        if not NAME.match(name) or name in ("front", "overhead", "room") or name.endswith("wrist"):
            raise TaskFileError(f"{w}: name: must be an identifier other than front, overhead, room and the wrist cameras")
        if "pos" not in entry:
            raise TaskFileError(f"{w}: pos: missing")
        if sum(k in entry for k in ("look_at", "xyaxes", "quat")) != 1:
            raise TaskFileError(f"{w}: give exactly one of look_at, xyaxes, quat")
        if "xyaxes" in entry:
            numbers(entry["xyaxes"], 6, f"{w}: xyaxes")
        if "quat" in entry:
            numbers(entry["quat"], 4, f"{w}: quat")
        if "fovy" in entry:
            numbers(entry["fovy"], 1, f"{w}: fovy")
        out.append(entry)
    return out


def read_subtasks(subtasks: Any, where: str) -> tuple[SubtaskSpec, ...]:
    """The `subtasks` list: {object, kind} in order, each with an optional `arm` (two-arm tasks)."""
    if not isinstance(subtasks, list):
        raise TaskFileError(f"{where}: subtasks: expected a list of {{object = ..., kind = ...}}")
    specs = []
    for i, entry in enumerate(subtasks):
        w = f"{where}: subtasks[{i}]"
        if not isinstance(entry, dict) or set(entry) - {"object", "kind", "arm"} or not {"object", "kind"} <= set(entry):
            raise TaskFileError(f"{w}: expected {{object = \"name\", kind = \"grasp|place|push\"}} (and arm = \"left|right\")")
        if entry["kind"] not in SUBTASK_KINDS:
            raise TaskFileError(f"{w}: kind: {entry['kind']!r} is not one of {', '.join(SUBTASK_KINDS)}")
        if "arm" in entry and not (isinstance(entry["arm"], str) and entry["arm"]):
            raise TaskFileError(f"{w}: arm: expected an arm's name, got {entry['arm']!r}")
        specs.append(SubtaskSpec(str(entry["object"]), entry["kind"], str(entry.get("arm", ""))))
    return tuple(specs)
