"""Tasks as files: a TOML file of objects, placement regions, a success expression and an instruction.

The format is docs/tasks.md's "Tasks as files". Loading is strict: an unknown
field, predicate or name, a bad mesh or objects that cannot be placed apart
raise TaskFileError with one line naming the file and the field. A file is
checked once at load by building it into an empty arena at a Panda-size layout.
The jobs live beside this class: the fields (file_schema), a Python judge
(file_judge_loader), shapes (file_geometry), placement, the model (file_model)
and the bundle (file_bundle).

A loaded task carries its own source (the TOML text and every file it names,
meshes with their convex parts included: `FileTask.bundle()`), which episodes
store so that replay, re-judging and generation need nothing else
(`task_from_bundle`).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from scenes.assembly.arena import Layout, make_arena, reference_layout
from scenes.assembly.robot import BUILTIN_ROBOTS
from scenes.errors import first_line
from scenes.tasks.base import Task
from scenes.tasks.constraints import TWO_ARMS, check_arms, read_constraints
from scenes.tasks.expr import ExpressionError, Node, parse, predicates
from scenes.tasks.file_bundle import make_bundle, unpack_bundle
from scenes.tasks.file_geometry import Geometry, object_geometry
from scenes.tasks.file_judge_loader import load_python_judge
from scenes.tasks.file_model import add_cameras, add_objects, add_regions, add_task_info
from scenes.tasks.file_schema import TASK_NAME, TOP_FIELDS, read_cameras, read_objects, read_regions, read_subtasks
from scenes.tasks.file_values import TaskFileError, length, numbers, required_str
from scenes.tasks.geometry import Units, model_units
from scenes.tasks.judge import Judge, JudgeError
from scenes.tasks.placement import Placed, place
from scenes.vary.variation import Ranges, VariationError, parse_ranges

BIMANUAL_ROBOTS = ("bimanual",)
REFERENCE_SIZE = 0.02  # m: the task-cube half-size that `scale = "robot"` lengths are written for
NOT_HELD: tuple[float, None] = (-math.inf, None)  # a hold timer not running: (last judged s, since s)

__all__ = ["FileTask", "TaskFileError", "load_task_file", "task_from_bundle"]


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
        name = required_str(raw, "name", where)
        if not TASK_NAME.match(name):
            raise TaskFileError(f"{where}: name: {name!r} must be lower-case letters, digits and _")
        instruction = required_str(raw, "instruction", where)
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
        self.hold = numbers(raw.get("hold", 0.0), 1, f"{where}: hold")[0]
        if self.hold < 0:
            raise TaskFileError(f"{where}: hold: must be >= 0 seconds")
        self.script = self.path.parent / raw["script"] if "script" in raw else None

        self.regions = read_regions(raw.get("region", []), where)
        self.objects = read_objects(raw.get("object", []), where, self.regions, self._file)
        self.cameras = read_cameras(raw.get("camera", []), where)
        self.variation = self._variation(raw.get("variation"))
        self.aliases: dict[str, str] = {}
        self.python_judge: Callable[[mujoco.MjModel, mujoco.MjData], bool] | None = None
        self.expr: Node | None = None
        success = required_str(raw, "success", where)
        if success.startswith("python:"):
            self.python_judge = load_python_judge(success, self.path, self.name, self.files, where)
        else:
            try:
                self.expr = parse(success)
            except ExpressionError as exc:
                raise TaskFileError(f"{where}: success: {exc}") from None
        self.subtasks = read_subtasks(raw.get("subtasks", []), where)
        check_arms(self.subtasks, TWO_ARMS if self.needs_bimanual else ("",), where)
        self.constraints = read_constraints(raw.get("constraint", []), self.subtasks, where)
        self._judges: dict[int, tuple[mujoco.MjModel, Judge]] = {}
        self._geometries: dict[Units, dict[str, Geometry]] = {}  # by units: a reset builds the scene anew
        self._held: dict[int, tuple[float, float | None]] = {}
        self._bundle: dict[str, Any] | None = None
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

    def _variation(self, table: Any) -> Ranges | None:
        """The `[variation]` table's ranges over the defaults (scenes.vary.variation), or None when the file has none."""
        if table is None:
            return None
        try:
            return parse_ranges(table, f"{self.where}: [variation]",
                                texture_file=lambda rel, w: self._file(rel, w, (".png",)))
        except VariationError as exc:
            raise TaskFileError(str(exc)) from None

    # -- units, placement, building ----------------------------------------------------------------------
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

    def geometries(self, layout: Layout) -> dict[str, Geometry]:
        """Every object's shape at `layout` (the same for every seed): resolved once per units for this task.

        Every reset and every new seed builds the scene again, and a mesh object's shape is a mesh and its
        convex parts read from disk (a Gymnasium check of one library task made 192 such reads, 2.4 s). A mesh
        file changed on disk is read again by the next process, not by this one.
        """
        u = self.units(layout)
        geos = self._geometries.get(u)
        if geos is None:
            geos = self._geometries[u] = {obj.name: object_geometry(obj, u) for obj in self.objects}
        return dict(geos)

    def place(self, layout: Layout, rng: np.random.Generator,
              geos: dict[str, Geometry] | None = None) -> tuple[dict[str, Placed], dict[str, Geometry]]:
        """Every object's place for this rng, in file order, never overlapping (TaskFileError if impossible)."""
        u = self.units(layout)
        gap = length(self.gap_raw, u, f"{self.where}: gap")
        geos = geos if geos is not None else self.geometries(layout)
        return place(self.objects, geos, self.regions, gap, u, rng), geos

    def build(self, spec: mujoco.MjSpec, layout: Layout, rng: np.random.Generator) -> dict[str, bytes]:
        """Add every object, region and camera to `spec`; returns the mesh assets they use."""
        u = self.units(layout)
        placed, geos = self.place(layout, rng)
        assets = add_objects(spec, self.objects, placed, geos, layout, u, self.aliases)
        add_regions(spec, self.regions, layout, u)
        add_cameras(spec, self.cameras, layout, u, self.where)
        add_task_info(spec, u, [self.aliases.get(o.name, o.name) for o in self.objects])
        if assets:
            spec.assets = {**spec.assets, **assets}
        return assets

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (to a worker) without the shapes resolved here: an mjcf object's MjSpec does not pickle."""
        return {**self.__dict__, "_geometries": {}}

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

    def _judge_for(self, model: mujoco.MjModel) -> Callable[[mujoco.MjData], bool]:
        entry = self._judges.get(id(model))
        if entry is None or entry[0] is not model:
            try:
                entry = (model, self.judge(model))
            except JudgeError as exc:
                raise TaskFileError(f"{self.where}: {exc}") from None
            self._judges = {id(model): entry}
        return entry[1]

    def success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        ok = self._judge_for(model)(data)
        if self.hold <= 0:
            return ok
        return self._timed(id(data), data.time, ok)

    def _timed(self, key: int, t: float, ok: bool) -> bool:
        """Success with its hold: `ok` now, and since at least `hold` s of sim time (per MjData, `key`)."""
        if not ok:
            self._held[key] = NOT_HELD
            return False
        held = self._held.get(key)
        since = held[1] if held is not None and t >= held[0] else None  # t < last: the data was reset
        if since is None:
            since = t
        self._held[key] = (t, since)
        return t - since >= self.hold - 1e-9

    def timer(self, model: mujoco.MjModel, data: mujoco.MjData) -> Callable[[], bool] | None:
        """For a task with a `hold`: `success(model, data)` as one call with everything bound, for the control
        tick, which judges it every tick to time the hold (the same state as `success`); None without a hold."""
        if self.hold <= 0:
            return None
        judge = self._judge_for(model)
        test = judge.bound(data) if isinstance(judge, Judge) else (lambda: judge(data))
        timed, key, held = self._timed, id(data), self._held

        def observe() -> bool:  # `_timed` with its usual case (not succeeding) inline: one call a tick
            if not test():
                held[key] = NOT_HELD  # as `_timed` stores it, with no time needed: nothing held to lose on a reset
                return False
            return timed(key, data.time, True)

        return observe

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
        names = model_names(model) | set(self.aliases)
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
        if self._bundle is None:
            self._bundle = make_bundle(self.name, self.path, self.toml_text, self.files)
        return self._bundle


def model_names(model: mujoco.MjModel) -> set[str]:
    """Every named body, site, geom and joint of `model`."""
    out = set()
    for kind, n in ((mujoco.mjtObj.mjOBJ_BODY, model.nbody), (mujoco.mjtObj.mjOBJ_SITE, model.nsite),
                    (mujoco.mjtObj.mjOBJ_GEOM, model.ngeom), (mujoco.mjtObj.mjOBJ_JOINT, model.njnt)):
        for i in range(n):
            name = mujoco.mj_id2name(model, kind, i)
            if name:
                out.add(name)
    return out


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


def task_from_bundle(bundle: Mapping[str, Any]) -> FileTask:
    """A task rebuilt from what an episode stored (`FileTask.bundle()`), written once under the user cache."""
    key = str(unpack_bundle(bundle))
    if key not in _FROM_BUNDLE:
        _FROM_BUNDLE[key] = load_task_file(key)
    return _FROM_BUNDLE[key]


_FROM_BUNDLE: dict[str, FileTask] = {}  # tasks already rebuilt from bundles in this process, by where they were written
