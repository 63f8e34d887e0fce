"""Tasks as files: a TOML file of objects, placement regions, a success expression and an instruction.

The format is the README's "Tasks as files". Loading is strict: an unknown
field, predicate or name, a bad mesh or objects that cannot be placed apart
raise TaskFileError with one line naming the file and the field. A file is
checked once at load by building it into an empty arena at a Panda-size layout.

A loaded task carries its own source (the TOML text and every file it names,
meshes with their convex parts included: `FileTask.bundle()`), which episodes
store so that replay, re-judging and generation need nothing else
(`task_from_bundle`).
"""

from __future__ import annotations

import base64
import hashlib
import importlib
import importlib.util
import math
import os
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from scenes.arena import TABLE_TOP, Layout, look_at_xyaxes, make_arena, reference_layout, yaw_quat
from scenes.errors import first_line
from scenes.robot import BUILTIN_ROBOTS, SceneError
from scenes.task_base import SUBTASK_KINDS, SubtaskSpec, Task
from scenes.task_expr import ExpressionError, Node, parse, predicates
from scenes.task_judge import OBJECTS_TEXT, UNITS_NUMERIC, Judge, JudgeError, Units, model_units
from scenes.variation import Ranges, VariationError, parse_ranges

BIMANUAL_ROBOTS = ("bimanual",)
REFERENCE_SIZE = 0.02  # m: the task-cube half-size that `scale = "robot"` lengths are written for
PLACE_TRIES = 1000
NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
TASK_NAME = re.compile(r"^[a-z0-9_]+$")
SHAPES = ("box", "cylinder", "sphere", "capsule", "bin", "mesh", "mjcf")
TOP_FIELDS = {"name", "instruction", "instructions", "family", "summary", "robots", "scale", "gap", "success", "hold", "script",
              "subtasks", "object", "region", "camera", "variation"}
OBJECT_FIELDS = {"name", *SHAPES, "scale", "wall", "rgba", "mass", "density", "friction", "fixed", "collide", "region", "on", "euler",
                 "z", "min_distance", "joints"}
REGION_FIELDS = {"name", "x", "y", "rgba"}
PLACE_FIELDS = {"x", "y", "yaw"}
CAMERA_FIELDS = {"name", "pos", "look_at", "xyaxes", "quat", "fovy"}
DEFAULT_FRICTION = (1.2, 0.01, 0.0005)
GREY = (0.55, 0.57, 0.6, 1.0)


class TaskFileError(SceneError):
    """A task file that cannot be used; the message is one line naming the file and the field."""


# -- lengths ---------------------------------------------------------------------------------------------

def length(value: Any, units: Units, where: str) -> float:
    """A length (m): a number (times the file's scale) or "K unit" with unit size|spread|reach|m."""
    if isinstance(value, bool):
        raise TaskFileError(f"{where}: expected a length, got {value!r}")
    if isinstance(value, (int, float)):
        return float(value) * units.scale
    if isinstance(value, str):
        m = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(size|spread|reach|m)\s*", value)
        if m:
            k, unit = float(m.group(1)), m.group(2)
            return k if unit == "m" else k * {"size": units.size, "spread": units.spread, "reach": units.reach}[unit]
    raise TaskFileError(f"{where}: expected a length (a number, or \"K size|spread|reach|m\"), got {value!r}")


def lengths(value: Any, n: int | tuple[int, ...], units: Units, where: str) -> list[float]:
    counts = (n,) if isinstance(n, int) else n
    if not isinstance(value, list):
        value = [value]
    if len(value) not in counts:
        raise TaskFileError(f"{where}: expected {' or '.join(map(str, counts))} value(s), got {len(value)}")
    return [length(v, units, where) for v in value]


def _numbers(value: Any, n: int | tuple[int, ...], where: str) -> list[float]:
    counts = (n,) if isinstance(n, int) else n
    if not isinstance(value, list):
        value = [value]
    if len(value) not in counts or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise TaskFileError(f"{where}: expected {' or '.join(map(str, counts))} number(s), got {value!r}")
    return [float(v) for v in value]


def _range(value: Any, units: Units | None, where: str) -> tuple[float, float]:
    """[lo, hi] (or a single value) as lengths, or as plain numbers when units is None."""
    if not isinstance(value, list):
        value = [value]
    if len(value) not in (1, 2):
        raise TaskFileError(f"{where}: expected [low, high] or one value, got {value!r}")
    vals = [length(v, units, where) if units is not None else _numbers(v, 1, where)[0] for v in value]
    lo, hi = vals[0], vals[-1]
    if hi < lo:
        raise TaskFileError(f"{where}: low {lo:g} is above high {hi:g}")
    return lo, hi


# -- the file's parts ------------------------------------------------------------------------------------

@dataclass
class ObjectDef:
    """One `[[object]]` entry as written (lengths still unresolved: they depend on the robot's layout)."""

    name: str
    shape: str
    raw: dict[str, Any]
    file: Path | None = None
    where: str = ""


@dataclass
class Placed:
    """Where placement put an object: centre offset (m, from the workspace centre), origin height, yaw."""

    xy: np.ndarray
    z: float
    yaw: float
    radius: float
    top: float  # height (m) of its top above the table
    on: str | None


@dataclass
class Geometry:
    """An object's resolved shape: footprint radius (m), extent below/above its origin (m), and parts."""

    radius: float
    below: float
    above: float
    mesh: tuple[np.ndarray, np.ndarray] | None = None
    parts: list | None = None
    mjcf: mujoco.MjSpec | None = None


class FileTask(Task):
    """A task read from a TOML file (see the module docstring)."""

    def __init__(self, path: Path, raw: dict[str, Any], text: str) -> None:
        self.path = Path(path)
        self.raw = raw
        self.toml_text = text
        self.files: dict[str, Path] = {}  # relative path as written -> file, for the bundle
        where = str(self.path)
        self.where = where
        unknown = sorted(set(raw) - TOP_FIELDS)
        if unknown:
            raise TaskFileError(f"{where}: unknown field '{unknown[0]}' (fields: {', '.join(sorted(TOP_FIELDS))})")
        name = _required_str(raw, "name", where)
        if not TASK_NAME.match(name):
            raise TaskFileError(f"{where}: name: {name!r} must be lower-case letters, digits and _")
        instruction = _required_str(raw, "instruction", where)
        instructions = raw.get("instructions", [])
        if not isinstance(instructions, list) or not all(isinstance(s, str) and s.strip() for s in instructions):
            raise TaskFileError(f"{where}: instructions: expected a list of non-empty strings")
        robots = raw.get("robots", [r for r in BUILTIN_ROBOTS if r not in BIMANUAL_ROBOTS])
        if not isinstance(robots, list) or not robots or not all(isinstance(r, str) for r in robots):
            raise TaskFileError(f"{where}: robots: expected a non-empty list of robot names")
        for r in robots:
            if r not in BUILTIN_ROBOTS:
                raise TaskFileError(f"{where}: robots: unknown robot {r!r} (built-ins: {', '.join(BUILTIN_ROBOTS)})")
        bimanual = [r in BIMANUAL_ROBOTS for r in robots]
        super().__init__(name=name, summary=str(raw.get("summary") or instruction), text=instruction,
                         needs_bimanual=all(bimanual), allows_bimanual=any(bimanual), subtasks=(),
                         family=str(raw.get("family", "custom")), instructions=tuple(instructions), robots=tuple(robots))
        for key in ("family", "summary", "script"):
            if key in raw and not isinstance(raw[key], str):
                raise TaskFileError(f"{where}: {key}: expected a string")
        scale = raw.get("scale", 1.0)
        if not (scale == "robot" or (isinstance(scale, (int, float)) and not isinstance(scale, bool) and scale > 0)):
            raise TaskFileError(f"{where}: scale: expected \"robot\" or a positive number, got {scale!r}")
        self.scale = scale
        self.gap_raw = raw.get("gap", 0.005)
        self.hold = _numbers(raw.get("hold", 0.0), 1, f"{where}: hold")[0]
        if self.hold < 0:
            raise TaskFileError(f"{where}: hold: must be >= 0 seconds")
        self.script = self.path.parent / raw["script"] if "script" in raw else None

        self.regions = self._regions(raw.get("region", []))
        self.objects = self._objects(raw.get("object", []))
        self.cameras = self._cameras(raw.get("camera", []))
        self.variation = self._variation(raw.get("variation"))
        self.aliases: dict[str, str] = {}
        self.python_judge: Callable[[mujoco.MjModel, mujoco.MjData], bool] | None = None
        self.expr: Node | None = None
        success = _required_str(raw, "success", where)
        if success.startswith("python:"):
            self.python_judge = self._python_judge(success)
        else:
            try:
                self.expr = parse(success)
            except ExpressionError as exc:
                raise TaskFileError(f"{where}: success: {exc}") from None
        subtasks = raw.get("subtasks", [])
        if not isinstance(subtasks, list):
            raise TaskFileError(f"{where}: subtasks: expected a list of {{object = ..., kind = ...}}")
        specs = []
        for i, entry in enumerate(subtasks):
            w = f"{where}: subtasks[{i}]"
            if not isinstance(entry, dict) or set(entry) - {"object", "kind"} or not {"object", "kind"} <= set(entry):
                raise TaskFileError(f"{w}: expected {{object = \"name\", kind = \"grasp|place|push\"}}")
            if entry["kind"] not in SUBTASK_KINDS:
                raise TaskFileError(f"{w}: kind: {entry['kind']!r} is not one of {', '.join(SUBTASK_KINDS)}")
            specs.append(SubtaskSpec(str(entry["object"]), entry["kind"]))
        self.subtasks = tuple(specs)
        self._judges: dict[int, tuple[mujoco.MjModel, Judge]] = {}
        self._held: dict[int, tuple[float, float | None]] = {}
        self._check()

    # -- reading -----------------------------------------------------------------------------------------
    def _file(self, rel: Any, where: str, suffixes: tuple[str, ...]) -> Path:
        if not isinstance(rel, str) or not rel:
            raise TaskFileError(f"{where}: expected a file name")
        path = (self.path.parent / rel).resolve()
        if path.suffix.lower() not in suffixes:
            raise TaskFileError(f"{where}: {rel!r} must be a {' or '.join(suffixes)} file")
        if not path.is_file():
            raise TaskFileError(f"{where}: {rel!r}: no such file (paths are relative to the task file)")
        self.files[rel] = path
        return path

    def _named_table(self, entry: Any, i: int, kind: str, fields: set[str]) -> tuple[str, str]:
        """(where, name) of the i-th [[kind]] table, refused when it is no table, has no name or an unknown field."""
        w = f"{self.where}: [[{kind}]] {i}"
        if not isinstance(entry, dict):
            raise TaskFileError(f"{w}: expected a table")
        name = _required_str(entry, "name", w)
        w = f"{self.where}: [[{kind}]] '{name}'"
        unknown = sorted(set(entry) - fields)
        if unknown:
            raise TaskFileError(f"{w}: unknown field '{unknown[0]}' (fields: {', '.join(sorted(fields))})")
        return w, name

    def _regions(self, entries: Any) -> dict[str, dict]:
        out: dict[str, dict] = {}
        if not isinstance(entries, list):
            raise TaskFileError(f"{self.where}: region: use [[region]] tables")
        for i, entry in enumerate(entries):
            w, name = self._named_table(entry, i, "region", REGION_FIELDS)
            if not NAME.match(name) or name in out:
                raise TaskFileError(f"{w}: name must be a unique identifier")
            for key in ("x", "y"):
                if key not in entry:
                    raise TaskFileError(f"{w}: {key}: missing")
            if "rgba" in entry:
                _numbers(entry["rgba"], 4, f"{w}: rgba")
            out[name] = entry
        return out

    def _objects(self, entries: Any) -> list[ObjectDef]:
        if not isinstance(entries, list) or not entries:
            raise TaskFileError(f"{self.where}: object: a task needs at least one [[object]]")
        out: list[ObjectDef] = []
        seen: set[str] = set()
        for i, entry in enumerate(entries):
            w, name = self._named_table(entry, i, "object", OBJECT_FIELDS)
            if not NAME.match(name) or name in seen or name in self.regions:
                raise TaskFileError(f"{w}: name: must be an identifier not used by another object or region")
            seen.add(name)
            shapes = [s for s in SHAPES if s in entry]
            if len(shapes) != 1:
                raise TaskFileError(f"{w}: give exactly one of {', '.join(SHAPES)}")
            shape = shapes[0]
            obj = ObjectDef(name, shape, entry, where=w)
            if shape == "mesh":
                obj.file = self._file(entry["mesh"], f"{w}: mesh", (".obj", ".stl"))
            elif shape == "mjcf":
                obj.file = self._file(entry["mjcf"], f"{w}: mjcf", (".xml",))
            if "scale" in entry and shape != "mesh":
                raise TaskFileError(f"{w}: scale: only a mesh object has a scale")
            if "joints" in entry and shape != "mjcf":
                raise TaskFileError(f"{w}: joints: only an mjcf object has joints")
            if "wall" in entry and shape != "bin":
                raise TaskFileError(f"{w}: wall: only a bin has a wall")
            if "mass" in entry and "density" in entry:
                raise TaskFileError(f"{w}: mass: give mass or density, not both")
            for key in ("mass", "density"):
                if key in entry and _numbers(entry[key], 1, f"{w}: {key}")[0] <= 0:
                    raise TaskFileError(f"{w}: {key}: must be > 0")
            if "rgba" in entry:
                _numbers(entry["rgba"], 4, f"{w}: rgba")
            if "friction" in entry:
                _numbers(entry["friction"], (1, 3), f"{w}: friction")
            if "euler" in entry:
                _numbers(entry["euler"], 3, f"{w}: euler")
            for key in ("fixed", "collide"):
                if key in entry and not isinstance(entry[key], bool):
                    raise TaskFileError(f"{w}: {key}: expected true or false")
            if "on" in entry and entry["on"] not in seen - {name}:
                raise TaskFileError(f"{w}: on: {entry['on']!r} is not an object named earlier in the file")
            region = entry.get("region")
            if isinstance(region, str):
                if region not in self.regions:
                    raise TaskFileError(f"{w}: region: no [[region]] named {region!r}")
            elif isinstance(region, dict):
                unknown = sorted(set(region) - PLACE_FIELDS)
                if unknown:
                    raise TaskFileError(f"{w}: region: unknown field '{unknown[0]}' (fields: x, y, yaw)")
            elif isinstance(region, list):
                if not region or not all(isinstance(r, str) and r in self.regions for r in region):
                    raise TaskFileError(f"{w}: region: a list must name [[region]]s")
            elif region is not None:
                raise TaskFileError(f"{w}: region: expected {{x = [lo, hi], y = [lo, hi], yaw = [lo, hi]}} or a region name")
            if "joints" in entry and not (isinstance(entry["joints"], dict)
                                          and all(isinstance(v, (int, float)) for v in entry["joints"].values())):
                raise TaskFileError(f"{w}: joints: expected {{joint_name = value}}")
            out.append(obj)
        return out

    def _cameras(self, entries: Any) -> list[dict]:
        if not isinstance(entries, list):
            raise TaskFileError(f"{self.where}: camera: use [[camera]] tables")
        out = []
        for i, entry in enumerate(entries):
            w, name = self._named_table(entry, i, "camera", CAMERA_FIELDS)
            if not NAME.match(name) or name in ("front", "overhead", "room") or name.endswith("wrist"):
                raise TaskFileError(f"{w}: name: must be an identifier other than front, overhead, room and the wrist cameras")
            if "pos" not in entry:
                raise TaskFileError(f"{w}: pos: missing")
            if sum(k in entry for k in ("look_at", "xyaxes", "quat")) != 1:
                raise TaskFileError(f"{w}: give exactly one of look_at, xyaxes, quat")
            if "xyaxes" in entry:
                _numbers(entry["xyaxes"], 6, f"{w}: xyaxes")
            if "quat" in entry:
                _numbers(entry["quat"], 4, f"{w}: quat")
            if "fovy" in entry:
                _numbers(entry["fovy"], 1, f"{w}: fovy")
            out.append(entry)
        return out

    def _variation(self, table: Any) -> Ranges | None:
        """The `[variation]` table's ranges over the defaults (scenes.variation), or None when the file has none."""
        if table is None:
            return None
        try:
            return parse_ranges(table, f"{self.where}: [variation]",
                                texture_file=lambda rel, w: self._file(rel, w, (".png",)))
        except VariationError as exc:
            raise TaskFileError(str(exc)) from None

    def _python_judge(self, success: str) -> Callable:
        parts = success.split(":")
        if len(parts) != 3 or not all(parts[1:]):
            raise TaskFileError(f"{self.where}: success: expected \"python:module:function\", got {success!r}")
        module_name, func = parts[1], parts[2]
        beside = self.path.parent / f"{module_name.replace('.', '/')}.py"
        try:
            if beside.is_file():
                self.files[beside.relative_to(self.path.parent).as_posix()] = beside
                spec = importlib.util.spec_from_file_location(f"teleop_task_{self.name}_{module_name}", beside)
                module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
                spec.loader.exec_module(module)  # type: ignore[union-attr]
            else:
                module = importlib.import_module(module_name)
        except Exception as exc:
            raise TaskFileError(f"{self.where}: success: module {module_name!r} does not import: {first_line(exc)}") from None
        fn = getattr(module, func, None)
        if not callable(fn):
            raise TaskFileError(f"{self.where}: success: module {module_name!r} has no function {func!r}")
        return fn

    # -- units and geometry ------------------------------------------------------------------------------
    def script_for(self, robot: str) -> Path | None:
        """The script that solves this task with `robot`: `<script>.<robot>.json` beside `script` when there is one.

        Scripts give lengths in metres and cannot scale with the robot's layout, so a
        smaller arm's sizes get a script of their own.
        """
        if self.script is None:
            return None
        own = self.script.with_name(f"{self.script.stem}.{robot}{self.script.suffix}")
        return own if own.exists() else self.script

    def units(self, layout: Layout) -> Units:
        scale = layout.size / REFERENCE_SIZE if self.scale == "robot" else float(self.scale)
        return Units(size=layout.size, spread=layout.spread, reach=layout.reach, scale=scale)

    def _geometry(self, obj: ObjectDef, u: Units) -> Geometry:
        raw, w = obj.raw, obj.where
        if obj.shape == "box":
            hx, hy, hz = lengths(raw["box"], 3, u, f"{w}: box")
            geo = Geometry(math.hypot(hx, hy), hz, hz)
        elif obj.shape in ("cylinder", "capsule"):
            r, h = lengths(raw[obj.shape], 2, u, f"{w}: {obj.shape}")
            geo = Geometry(r, h + (r if obj.shape == "capsule" else 0.0), h + (r if obj.shape == "capsule" else 0.0))
        elif obj.shape == "sphere":
            (r,) = lengths(raw["sphere"], 1, u, f"{w}: sphere")
            geo = Geometry(r, r, r)
        elif obj.shape == "bin":
            hx, hy, height = lengths(raw["bin"], 3, u, f"{w}: bin")
            wall = length(raw.get("wall", 0.004), u, f"{w}: wall") if "wall" in raw else 0.004
            geo = Geometry(math.hypot(hx + 2 * wall, hy + 2 * wall), 0.0, height)
        elif obj.shape == "mesh":
            from scenes.mesh_collision import MeshError, convex_parts, load_mesh

            scale = np.asarray(_numbers(raw.get("scale", 1.0), (1, 3), f"{w}: scale"), float) * u.scale
            try:
                vertices, faces = load_mesh(obj.file)  # type: ignore[arg-type]
                parts = convex_parts(obj.file)  # type: ignore[arg-type]
            except MeshError as exc:
                raise TaskFileError(f"{w}: mesh: {exc}") from None
            v = vertices * scale
            rot = _euler_matrix(raw.get("euler", [0.0, 0.0, 0.0]))
            vr = v @ rot.T
            geo = Geometry(float(np.max(np.linalg.norm(vr[:, :2], axis=1))), float(-vr[:, 2].min()), float(vr[:, 2].max()),
                           mesh=(v, faces), parts=[(pv * scale, pf) for pv, pf in parts])
        else:
            child = self._mjcf_spec(obj, u)
            try:
                model = child.copy().compile()
            except Exception as exc:
                raise TaskFileError(f"{w}: mjcf: does not compile: {first_line(exc)}") from None
            data = mujoco.MjData(model)
            mujoco.mj_kinematics(model, data)
            radius, hi = 0.0, 0.0
            for g in range(model.ngeom):
                p, rb = data.geom_xpos[g], float(model.geom_rbound[g])
                radius = max(radius, float(np.linalg.norm(p[:2])) + rb)
                hi = max(hi, float(p[2]) + rb)
            geo = Geometry(radius, 0.0, hi, mjcf=child)  # an mjcf thing's origin stands on the table
        return geo

    def _mjcf_spec(self, obj: ObjectDef, u: Units) -> mujoco.MjSpec:
        w = f"{obj.where}: mjcf"
        try:
            child = mujoco.MjSpec.from_file(str(obj.file))
        except Exception as exc:
            raise TaskFileError(f"{w}: does not load: {first_line(exc)}") from None
        if any(m.file for m in child.meshes) or any(t.file for t in child.textures):
            raise TaskFileError(f"{w}: an mjcf object may not reference files (use a mesh object for meshes)")
        f = u.scale
        if f != 1.0:
            for b in child.bodies[1:]:
                b.pos = np.asarray(b.pos) * f
            for g in child.geoms:
                g.size = np.asarray(g.size) * f
                g.pos = np.asarray(g.pos) * f
                if not np.isnan(g.fromto[0]):
                    g.fromto = np.asarray(g.fromto) * f
            for s in child.sites:
                s.size = np.asarray(s.size) * f
                s.pos = np.asarray(s.pos) * f
            for j in child.joints:
                j.pos = np.asarray(j.pos) * f
                if int(j.type) == int(mujoco.mjtJoint.mjJNT_SLIDE):
                    j.range = np.asarray(j.range) * f
        return child

    # -- placement ---------------------------------------------------------------------------------------
    def _place_box(self, obj: ObjectDef, u: Units, rng: np.random.Generator) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
        region = obj.raw.get("region")
        w = f"{obj.where}: region"
        if isinstance(region, list):
            region = region[int(rng.integers(len(region)))] if len(region) > 1 else region[0]
        if isinstance(region, str):
            reg = self.regions[region]
            return (_range(reg["x"], u, f"{w} '{region}': x"), _range(reg["y"], u, f"{w} '{region}': y"), (0.0, 0.0))
        if region is None:
            region = {} if "on" in obj.raw else {"x": ["-1 spread", "1 spread"], "y": ["-1 spread", "1 spread"]}
        x = _range(region.get("x", 0.0), u, f"{w}: x")
        y = _range(region.get("y", 0.0), u, f"{w}: y")
        yaw = _range(region.get("yaw", 0.0), None, f"{w}: yaw")
        return x, y, yaw

    def place(self, layout: Layout, rng: np.random.Generator) -> tuple[dict[str, Placed], dict[str, Geometry]]:
        """Every object's place for this rng, in file order, never overlapping (TaskFileError if impossible)."""
        u = self.units(layout)
        gap = length(self.gap_raw, u, f"{self.where}: gap")
        placed: dict[str, Placed] = {}
        geos: dict[str, Geometry] = {}
        for obj in self.objects:
            geo = geos[obj.name] = self._geometry(obj, u)
            on = obj.raw.get("on")
            min_d = length(obj.raw["min_distance"], u, f"{obj.where}: min_distance") if "min_distance" in obj.raw else 0.0
            z_over = length(obj.raw["z"], u, f"{obj.where}: z") if "z" in obj.raw else None
            clash = ""
            for _ in range(PLACE_TRIES):
                (xl, xh), (yl, yh), (al, ah) = self._place_box(obj, u, rng)  # a list of regions: one drawn per try
                x = xl if xl == xh else float(rng.uniform(xl, xh))
                y = yl if yl == yh else float(rng.uniform(yl, yh))
                yaw = al if al == ah else float(rng.uniform(al, ah))
                base = placed[on] if on else None
                xy = np.array([x, y]) + (base.xy if base is not None else 0.0)
                floor = base.top if base is not None else 0.0
                z = floor + (z_over if z_over is not None else geo.below)
                clash = ""
                if on is None:
                    for other_name, other in placed.items():
                        if other.on is not None:
                            continue
                        other_min = self._min_distance(other_name, u)
                        need = max(geo.radius + other.radius + gap, min_d, other_min)
                        if np.linalg.norm(xy - other.xy) <= need:
                            clash = other_name
                            break
                if not clash:
                    placed[obj.name] = Placed(xy, z, yaw, geo.radius, z + geo.above, on)
                    break
            else:
                raise TaskFileError(f"{obj.where}: region: cannot place it without overlapping '{clash}' ({PLACE_TRIES} tries)")
        return placed, geos

    def _min_distance(self, name: str, u: Units) -> float:
        raw = next(o.raw for o in self.objects if o.name == name)
        return length(raw["min_distance"], u, "min_distance") if "min_distance" in raw else 0.0

    # -- building ----------------------------------------------------------------------------------------
    def build(self, spec: mujoco.MjSpec, layout: Layout, rng: np.random.Generator) -> dict[str, bytes]:
        """Add every object, region and camera to `spec`; returns the mesh assets they use."""
        u = self.units(layout)
        placed, geos = self.place(layout, rng)
        assets: dict[str, bytes] = {}
        cx, cy = layout.center
        for obj in self.objects:
            p, geo = placed[obj.name], geos[obj.name]
            pos = [cx + float(p.xy[0]), cy + float(p.xy[1]), TABLE_TOP + p.z]
            quat = _quat(obj.raw.get("euler"), p.yaw)
            self._add_object(spec, obj, geo, pos, quat, u, assets)
        for name, reg in self.regions.items():
            (xl, xh), (yl, yh) = _range(reg["x"], u, name), _range(reg["y"], u, name)
            center = [cx + (xl + xh) / 2, cy + (yl + yh) / 2, TABLE_TOP + 0.0005]
            half = [max((xh - xl) / 2, 0.0005), max((yh - yl) / 2, 0.0005), 0.0005]
            spec.worldbody.add_site(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, pos=center, size=half,
                                    rgba=reg.get("rgba", [0, 0, 0, 0]), group=0 if "rgba" in reg else 5)
        for cam in self.cameras:
            w = f"{self.where}: [[camera]] '{cam['name']}'"
            rel = lengths(cam["pos"], 3, u, f"{w}: pos")
            eye = np.array([cx + rel[0], cy + rel[1], TABLE_TOP + rel[2]])
            kwargs: dict[str, Any] = {"name": cam["name"], "pos": eye, "fovy": float(cam.get("fovy", 45.0))}
            if "look_at" in cam:
                t = lengths(cam["look_at"], 3, u, f"{w}: look_at")
                target = np.array([cx + t[0], cy + t[1], TABLE_TOP + t[2]])
                if np.linalg.norm(target - eye) < 1e-6:
                    raise TaskFileError(f"{w}: look_at: the camera looks at its own position")
                kwargs["xyaxes"] = look_at_xyaxes(eye, target)
            elif "xyaxes" in cam:
                kwargs["xyaxes"] = cam["xyaxes"]
            else:
                kwargs["quat"] = cam["quat"]
            spec.worldbody.add_camera(**kwargs)
        spec.add_numeric(name=UNITS_NUMERIC, data=u.as_list(), size=4)
        # the objects' bodies, fixed ones included (a bin placed per seed is state a policy needs)
        spec.add_text(name=OBJECTS_TEXT, data=",".join(self.aliases.get(o.name, o.name) for o in self.objects))  # never empty
        if assets:
            spec.assets = {**spec.assets, **assets}
        return assets

    def _add_object(self, spec: mujoco.MjSpec, obj: ObjectDef, geo: Geometry, pos: list[float], quat: list[float] | None,
                    u: Units, assets: dict[str, bytes]) -> None:
        raw, name = obj.raw, obj.name
        fixed = bool(raw.get("fixed", False))
        rgba = raw.get("rgba", list(GREY) if obj.shape in ("bin", "mjcf") else [0.85, 0.2, 0.15, 1.0])
        friction = raw.get("friction", list(DEFAULT_FRICTION))
        friction = friction * 3 if len(friction) == 1 else friction
        collide = raw.get("collide", True)
        if obj.shape == "mjcf":
            frame = spec.worldbody.add_frame(pos=pos, **({"quat": quat} if quat is not None else {}))
            child = geo.mjcf.copy() if geo.mjcf is not None else self._mjcf_spec(obj, u)
            roots = [b.name for b in child.worldbody.bodies]
            prefix = f"{name}::"
            spec.attach(child, prefix=prefix, frame=frame)
            for group in (spec.bodies, spec.geoms, spec.sites, spec.joints, spec.cameras, spec.lights, spec.actuators,
                          spec.tendons, spec.equalities, spec.sensors, spec.excludes, spec.meshes, spec.materials, spec.textures):
                for e in group:
                    if e.name.startswith(prefix):
                        e.name = e.name[len(prefix):]
            if roots and name not in roots:
                self.aliases[name] = roots[0]
            return
        body = spec.worldbody.add_body(name=name, pos=pos, **({"quat": quat} if quat is not None else {}))
        if not fixed:
            body.add_freejoint(name=f"{name}_joint")
        common: dict[str, Any] = {"rgba": rgba, "friction": friction}
        if not collide:
            common.update(contype=0, conaffinity=0)
        mass = raw.get("mass")
        density = raw.get("density")
        if obj.shape in ("box", "cylinder", "sphere", "capsule"):
            kind = {"box": mujoco.mjtGeom.mjGEOM_BOX, "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
                    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE, "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE}[obj.shape]
            n = {"box": 3, "cylinder": 2, "capsule": 2, "sphere": 1}[obj.shape]
            size = lengths(raw[obj.shape], n, u, f"{obj.where}: {obj.shape}")
            extra = {"mass": float(mass)} if mass is not None else {"density": float(density if density is not None else 600.0)}
            body.add_geom(name=f"{name}_geom", type=kind, size=size + [0.0] * (3 - n), condim=4, **common, **extra)
        elif obj.shape == "bin":
            hx, hy, height = lengths(raw["bin"], 3, u, f"{obj.where}: bin")
            wall = length(raw["wall"], u, f"{obj.where}: wall") if "wall" in raw else 0.004
            body.add_geom(name=f"{name}_floor", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx + wall, hy + wall, wall], pos=[0, 0, wall], **common)
            for i, (dx, dy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
                size = [wall, hy + wall, height / 2] if dx else [hx + wall, wall, height / 2]
                body.add_geom(name=f"{name}_wall{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=size,
                              pos=[dx * (hx + wall), dy * (hy + wall), height / 2], **common)
            body.add_site(name=f"{name}_inside", pos=[0, 0, height / 2], size=[hx, hy, height / 2], type=mujoco.mjtGeom.mjGEOM_BOX,
                          rgba=[0, 0, 0, 0], group=5)
        else:  # mesh: the mesh is seen, its convex parts collide
            from scenes.mesh_collision import parts_obj_bytes

            v, f = geo.mesh  # type: ignore[misc]
            visual = f"task_{name}_visual.obj"
            assets[visual] = parts_obj_bytes([(v, f)])[0]
            spec.add_mesh(name=f"{name}_visual", file=visual, inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL)
            body.add_geom(name=f"{name}_visual", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}_visual", rgba=rgba,
                          contype=0, conaffinity=0, group=2, density=0.0)
            parts = geo.parts or []
            part_mass = {"mass": float(mass) / len(parts)} if mass is not None else {"density": float(density if density is not None else 400.0)}
            for i, data in enumerate(parts_obj_bytes(parts)):
                file = f"task_{name}_part{i}.obj"
                assets[file] = data
                spec.add_mesh(name=f"{name}_part{i}", file=file)
                body.add_geom(name=f"{name}_col{i}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}_part{i}", group=3, condim=4,
                              **common, **part_mass)

    def initial_joints(self) -> dict[str, float]:
        """Joint positions (rad or m) the file sets for its mjcf objects (`joints = {...}`)."""
        out: dict[str, float] = {}
        for obj in self.objects:
            out.update({k: float(v) for k, v in obj.raw.get("joints", {}).items()})
        return out

    # -- judging -----------------------------------------------------------------------------------------
    def judge(self, model: mujoco.MjModel, units: Units | None = None) -> Callable[[mujoco.MjData], bool]:
        """The success test (without hold) bound to `model`; units default to those the scene stored in it."""
        if self.python_judge is not None:
            fn = self.python_judge
            return lambda data: bool(fn(model, data))
        units = units or model_units(model)
        if units is None:
            raise TaskFileError(f"{self.where}: the model holds no task units; pass the robot's layout units")
        return Judge(self.expr, model, units, self.aliases, tuple(o.name for o in self.objects))  # type: ignore[arg-type]

    def success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        entry = self._judges.get(id(model))
        if entry is None or entry[0] is not model:
            try:
                entry = (model, self.judge(model))
            except JudgeError as exc:
                raise TaskFileError(f"{self.where}: {exc}") from None
            self._judges = {id(model): entry}
        ok = entry[1](data)
        if self.hold <= 0:
            return ok
        t = float(data.time)
        last, since = self._held.get(id(data), (-math.inf, None))
        if t < last:
            since = None  # the data was reset
        since = (since if since is not None else t) if ok else None
        self._held[id(data)] = (t, since)
        return bool(ok and t - since >= self.hold - 1e-9)  # type: ignore[operator]

    # -- checking ----------------------------------------------------------------------------------------
    def _check(self) -> None:
        """Build into an empty arena at the reference layout: meshes load, objects place apart, names exist."""
        layout = reference_layout()
        spec = make_arena(layout, 0.002)
        assets = self.build(spec, layout, np.random.default_rng(0))
        try:
            model = mujoco.MjModel.from_xml_string(spec.to_xml(), assets)
        except Exception as exc:
            raise TaskFileError(f"{self.where}: the task does not compile: {first_line(exc)}") from None
        names = _model_names(model) | set(self.aliases)
        for name in self.initial_joints():
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name) < 0:
                raise TaskFileError(f"{self.where}: joints: no joint named {name!r} in the task's mjcf objects")
        if self.expr is not None:
            for pred in predicates(self.expr):
                for arg in pred.args:
                    if isinstance(arg, str) and arg not in names and "/" not in arg:
                        raise TaskFileError(f"{self.where}: success: {pred.name}: unknown object {arg!r} "
                                            f"(objects: {', '.join(o.name for o in self.objects)})")
            try:
                Judge(self.expr, model, self.units(layout), self.aliases, ())
            except JudgeError as exc:
                if "/" not in str(exc):
                    raise TaskFileError(f"{self.where}: {exc}") from None
        for i, sub in enumerate(self.subtasks):
            if sub.object not in names and "/" not in sub.object:
                raise TaskFileError(f"{self.where}: subtasks[{i}]: object: unknown object {sub.object!r}")
        self._judges.clear()

    # -- embedding ---------------------------------------------------------------------------------------
    def bundle(self) -> dict[str, Any]:
        """The task's source as JSON: the TOML text and every file it names (base64), convex parts included."""
        if getattr(self, "_bundle", None) is None:
            self._bundle = self._make_bundle()
        return self._bundle

    def _make_bundle(self) -> dict[str, Any]:
        from scenes.mesh_collision import cache_key, cached_parts, shipped_path

        files: dict[str, str] = {}
        for rel, path in self.files.items():
            files[rel] = base64.b64encode(path.read_bytes()).decode()
            if path.suffix.lower() in (".obj", ".stl"):
                key = cache_key(path)
                shipped = shipped_path(path, key)
                parts_rel = str(Path(rel).with_name(shipped.name).as_posix())
                if shipped.is_file():
                    files[parts_rel] = base64.b64encode(shipped.read_bytes()).decode()
                else:
                    parts = cached_parts(path)
                    if parts is not None:
                        import io

                        arrays = {}
                        for i, (v, f) in enumerate(parts):
                            arrays[f"v{i}"], arrays[f"f{i}"] = v, f
                        buffer = io.BytesIO()
                        np.savez_compressed(buffer, count=np.array(len(parts)), **arrays)
                        files[parts_rel] = base64.b64encode(buffer.getvalue()).decode()
        return {"name": self.name, "file": self.path.name, "toml": self.toml_text, "files": files}


def _required_str(raw: Mapping[str, Any], key: str, where: str) -> str:
    value = raw.get(key)
    if not isinstance(value, str) or not value.strip():
        raise TaskFileError(f"{where}: {key}: missing (a non-empty string)")
    return value


def _model_names(model: mujoco.MjModel) -> set[str]:
    out = set()
    for kind, n in ((mujoco.mjtObj.mjOBJ_BODY, model.nbody), (mujoco.mjtObj.mjOBJ_SITE, model.nsite),
                    (mujoco.mjtObj.mjOBJ_GEOM, model.ngeom), (mujoco.mjtObj.mjOBJ_JOINT, model.njnt)):
        for i in range(n):
            name = mujoco.mj_id2name(model, kind, i)
            if name:
                out.add(name)
    return out


def _euler_matrix(euler: Any) -> np.ndarray:
    quat = np.zeros(4)
    mujoco.mju_euler2Quat(quat, np.asarray(euler, float), "xyz")
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, quat)
    return mat.reshape(3, 3)


def _quat(euler: Any, yaw: float) -> list[float] | None:
    """Body quaternion: the fixed `euler` (xyz, rad) then the sampled yaw about world z; None for identity."""
    if euler is None and yaw == 0.0:
        return None
    q = np.array([1.0, 0.0, 0.0, 0.0])
    if euler is not None:
        mujoco.mju_euler2Quat(q, np.asarray(euler, float), "xyz")
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(yaw_quat(yaw)), q)
    return [float(v) for v in out]


# -- loading -----------------------------------------------------------------------------------------------

def load_task_file(path: str | Path) -> FileTask:
    """Read and check a task file; TaskFileError (one line, naming the field) if it is not usable."""
    path = Path(path)
    if not path.is_file():
        raise TaskFileError(f"{path}: no such task file")
    try:
        text = path.read_text()
        raw = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise TaskFileError(f"{path}: not valid TOML: {first_line(exc)}") from None
    return FileTask(path, raw, text)


def bundle_dir() -> Path:
    root = os.environ.get("TELEOP_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "mujoco-teleop") / "tasks"


def task_from_bundle(bundle: Mapping[str, Any]) -> FileTask:
    """A task rebuilt from what an episode stored (`FileTask.bundle()`), written once under the user cache."""
    try:
        text = str(bundle["toml"])
        files = {str(k): base64.b64decode(v) for k, v in dict(bundle.get("files") or {}).items()}
        file_name = Path(str(bundle.get("file") or "task.toml")).name
    except (KeyError, TypeError, ValueError) as exc:
        raise TaskFileError(f"the episode's task_file is damaged: {first_line(exc)}") from None
    digest = hashlib.sha256(text.encode())
    for rel in sorted(files):
        digest.update(rel.encode() + b"\0" + files[rel])
    depth = max([Path(rel).parts.count("..") for rel in files] + [0])
    root = bundle_dir() / digest.hexdigest()[:16]
    home = root.joinpath(*(["t"] * depth))
    for rel, data in files.items():
        target = Path(os.path.normpath(home / rel))
        if root not in target.parents:
            raise TaskFileError(f"the episode's task_file names a file outside its folder: {rel!r}")
        if not target.is_file() or target.read_bytes() != data:
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_suffix(target.suffix + ".tmp")
            tmp.write_bytes(data)
            os.replace(tmp, target)
    toml_path = home / file_name
    home.mkdir(parents=True, exist_ok=True)
    if not toml_path.is_file() or toml_path.read_text() != text:
        toml_path.write_text(text)
    key = str(toml_path)
    if key not in _FROM_BUNDLE:
        _FROM_BUNDLE[key] = load_task_file(toml_path)
    return _FROM_BUNDLE[key]


_FROM_BUNDLE: dict[str, FileTask] = {}  # tasks already rebuilt from bundles in this process, by where they were written
