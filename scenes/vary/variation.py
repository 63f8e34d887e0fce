"""What may vary, by how much, and from which seed: the ranges a task declares and the seeds looks come from.

Two stages. Physics (object size, mass, friction, damping of articulated joints,
physical distractors) changes the dynamics, so it is sampled when a scene is built
(`teleop generate|run|serve --vary physics`) and lives in the model the episode
embeds: replay stays bit-exact (scenes.vary.physics). Looks (lights, colours,
textures, camera jitter, visual-only distractors) change only pictures, so they are
sampled at export from the recorded model, many per episode (scenes.vary.looks).

Ranges come from the task file's `[variation]` table, else the defaults here; CLI
flags (`--vary-range KEY=LO,HI`, `--texture FILE`) override single keys.

Seeds. Physics for scene seed s draws from the stream (PHYSICS, split, s); a look
from (LOOKS, look seed, scene seed). Training looks seeds are 0 <= L < HELD_OUT_BASE
(export: `--looks-seed S` gives variant j the look seed S + j) and held-out ones
HELD_OUT_BASE + S (`teleop eval`), so evaluation never sees a training look; the
physics split tag does the same for physics.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from scenes.errors import TeleopError
from scenes.vary.textures import PROCEDURAL, is_png

PHYSICS_KINDS = ("size", "mass", "friction", "damping", "distractors")
LOOKS_KINDS = ("lights", "colors", "textures", "cameras", "distractors")
GROUPS = {"physics": ("size", "mass", "friction", "damping"), "looks": ("lights", "colors", "textures", "cameras")}
STAGES = ("generation", "export", "eval")
SPLITS = ("train", "held_out")
HELD_OUT_BASE = 1_000_000_000  # looks seeds from here up are held out (evaluation); below, training (export)
PHYSICS_STREAM = 0x50485953  # "PHYS": physics draws never share a stream with placement or looks
LOOKS_STREAM = 0x4C4F4F4B  # "LOOK"
DISTRACTOR_PREFIX = "distractor_"  # bodies and geoms variation adds: never a task object, never in environment_state
VARIATION_KEY = "variation"  # episode metadata key (and LeRobot episode column) holding what was varied


class VariationError(TeleopError, ValueError):
    """A range, a `--vary` word or a texture that cannot be used; one line naming it."""


@dataclass(frozen=True)
class Ranges:
    """How much each kind may vary. Factors multiply the task's own value; counts are whole numbers.

    Physics: size, mass, friction (sliding), damping (articulated joints' damping) factors;
    distractors: how many (physical at generation, visual-only at export), each
    distractor_size task-cube half-sizes across. Looks: lights (how many replace the
    room's), each within light_spread m of the workspace centre in x and y, light_height m
    above the table, light_intensity its diffuse level (0..1); hue: the largest shift of an
    object's hue (fraction of the colour circle: small, so a red cube stays red);
    brightness: factor on objects' colour; table_saturation / table_value: the table's
    colour (any hue); textures: procedural kinds for table, floor and objects, plus
    texture_files (PNG, named by the user); camera_pos (m) and camera_angle (deg): the
    largest jitter of each camera's position and direction.
    """

    size: tuple[float, float] = (0.9, 1.1)
    mass: tuple[float, float] = (0.7, 1.5)
    friction: tuple[float, float] = (0.7, 1.3)
    damping: tuple[float, float] = (0.5, 2.0)
    distractors: tuple[int, int] = (1, 3)
    distractor_size: tuple[float, float] = (0.6, 1.5)
    lights: tuple[int, int] = (1, 3)
    light_spread: float = 1.0
    light_height: tuple[float, float] = (1.0, 2.5)
    light_intensity: tuple[float, float] = (0.3, 0.75)
    hue: float = 0.03
    brightness: tuple[float, float] = (0.75, 1.25)
    table_saturation: tuple[float, float] = (0.0, 0.5)
    table_value: tuple[float, float] = (0.3, 0.85)
    textures: tuple[str, ...] = PROCEDURAL
    texture_files: tuple[tuple[str, bytes], ...] = field(default=(), repr=False)  # (name, PNG bytes)
    camera_pos: float = 0.02
    camera_angle: float = 2.0

    def to_json(self) -> dict[str, Any]:
        """The ranges as recorded (texture files by name)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "texture_files":
                out[f.name] = [name for name, _ in value]
            else:
                out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    @property
    def texture_data(self) -> dict[str, bytes]:
        return dict(self.texture_files)


DEFAULT_RANGES = Ranges()

# key -> (kind of value, least allowed, most allowed, unit for messages)
_PAIR_RULES: dict[str, tuple[str, float, float, str]] = {
    "size": ("factor", 0.0, math.inf, "a factor > 0"),
    "mass": ("factor", 0.0, math.inf, "a factor > 0"),
    "friction": ("factor", 0.0, math.inf, "a factor > 0"),
    "damping": ("factor0", 0.0, math.inf, "a factor >= 0"),
    "distractors": ("count", 0, 20, "a count 0..20"),
    "distractor_size": ("factor", 0.0, 10.0, "task-cube sizes > 0"),
    "lights": ("count", 0, 8, "a count 0..8"),
    "light_height": ("factor", 0.0, 20.0, "m > 0"),
    "light_intensity": ("factor0", 0.0, 1.0, "a level 0..1"),
    "brightness": ("factor", 0.0, 4.0, "a factor > 0"),
    "table_saturation": ("factor0", 0.0, 1.0, "0..1"),
    "table_value": ("factor0", 0.0, 1.0, "0..1"),
}
_SCALAR_RULES: dict[str, tuple[float, float, str]] = {
    "light_spread": (0.0, 10.0, "m, 0..10"),
    "hue": (0.0, 0.5, "a fraction of the colour circle, 0..0.5"),
    "camera_pos": (0.0, 0.5, "m, 0..0.5"),
    "camera_angle": (0.0, 45.0, "deg, 0..45"),
}
KEYS = (*_PAIR_RULES, *_SCALAR_RULES, "textures", "texture_files")


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise VariationError(f"{where}: expected a number, got {value!r}")
    return float(value)


def _pair(key: str, value: Any, where: str) -> tuple[float, float] | tuple[int, int]:
    kind, least, most, unit = _PAIR_RULES[key]
    values = value if isinstance(value, (list, tuple)) else [value]
    if len(values) not in (1, 2):
        raise VariationError(f"{where}: expected [low, high] or one value ({unit}), got {value!r}")
    lo, hi = (_number(v, where) for v in (values[0], values[-1]))
    for v in (lo, hi):
        bad = v <= least if kind == "factor" else v < least
        if bad or v > most:
            raise VariationError(f"{where}: {v:g} is out of range ({unit})")
    if hi < lo:
        raise VariationError(f"{where}: low {lo:g} is above high {hi:g}")
    if kind == "count":
        if lo != int(lo) or hi != int(hi):
            raise VariationError(f"{where}: expected whole numbers ({unit}), got {value!r}")
        return int(lo), int(hi)
    return lo, hi


def _scalar(key: str, value: Any, where: str) -> float:
    least, most, unit = _SCALAR_RULES[key]
    v = _number(value, where)
    if not least <= v <= most:
        raise VariationError(f"{where}: {v:g} is out of range ({unit})")
    return v


def _kinds_of_textures(value: Any, where: str) -> tuple[str, ...]:
    names = [value] if isinstance(value, str) else value
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise VariationError(f"{where}: expected a list of {', '.join(PROCEDURAL)}")
    for n in names:
        if n not in PROCEDURAL:
            raise VariationError(f"{where}: unknown procedural texture {n!r} (kinds: {', '.join(PROCEDURAL)})")
    return tuple(dict.fromkeys(names))


def read_texture(path: Path, where: str) -> tuple[str, bytes]:
    """(file name, PNG bytes) of a texture image the user named; VariationError if missing or not a PNG."""
    path = Path(path)
    if not path.is_file():
        raise VariationError(f"{where}: texture file {str(path)!r} not found")
    data = path.read_bytes()
    if not is_png(data):
        raise VariationError(f"{where}: texture file {str(path)!r} is not a PNG image")
    return path.name, data


def parse_ranges(table: Any, where: str, base: Ranges = DEFAULT_RANGES,
                 texture_file: Callable[[str, str], Path] | None = None) -> Ranges:
    """A `[variation]` table (or CLI overrides as a dict) over `base`; VariationError names the key.

    texture_file(rel, where) -> the path of a texture named relative to the task file.
    """
    if not isinstance(table, Mapping):
        raise VariationError(f"{where}: expected a table of ranges")
    changes: dict[str, Any] = {}
    for key, value in table.items():
        w = f"{where}: {key}"
        if key in _PAIR_RULES:
            changes[key] = _pair(key, value, w)
        elif key in _SCALAR_RULES:
            changes[key] = _scalar(key, value, w)
        elif key == "textures":
            changes[key] = _kinds_of_textures(value, w)
        elif key == "texture_files":
            names = [value] if isinstance(value, str) else value
            if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) and n for n in names):
                raise VariationError(f"{w}: expected a list of PNG file names")
            resolve = texture_file or (lambda rel, _w: Path(rel))
            changes[key] = tuple(read_texture(resolve(n, w), w) for n in names)
        else:
            raise VariationError(f"{w}: unknown key (keys: {', '.join(KEYS)})")
    return replace(base, **changes)


def parse_range_flags(flags: Iterable[str]) -> dict[str, Any]:
    """`--vary-range KEY=LO,HI` (or KEY=V; textures=checker,noise) flags as a table for parse_ranges (checked there)."""
    table: dict[str, Any] = {}
    for flag in flags:
        key, eq, text = flag.partition("=")
        key = key.strip()
        if not eq or not key:
            raise VariationError(f"--vary-range {flag!r}: expected KEY=LOW,HIGH or KEY=VALUE (keys: {', '.join(KEYS)})")
        if key not in KEYS or key == "texture_files":
            raise VariationError(f"--vary-range {flag!r}: unknown key {key!r} (keys: {', '.join(k for k in KEYS if k != 'texture_files')}; "
                                 "image textures: --texture FILE)")
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if key == "textures":
            table[key] = parts
            continue
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise VariationError(f"--vary-range {flag!r}: expected numbers") from None
        table[key] = values if len(values) != 1 else values[0]
    parse_ranges(table, "--vary-range")  # checked now: a bad value answers before anything runs
    return table


def parse_vary(text: str | None, stage: str) -> tuple[str, ...]:
    """`--vary` words for a stage ('generation': physics; 'export': looks; 'eval': both) -> kinds, in order."""
    if text is None or not text.strip():
        return ()
    allowed = {"generation": PHYSICS_KINDS, "export": LOOKS_KINDS, "eval": tuple(dict.fromkeys(PHYSICS_KINDS + LOOKS_KINDS))}[stage]
    groups = {"generation": ("physics",), "export": ("looks",), "eval": ("physics", "looks")}[stage]
    out: list[str] = []
    for word in (w.strip() for w in text.split(",")):
        if not word:
            continue
        if word in groups:
            out += GROUPS[word]
        elif word in allowed:
            out.append(word)
        else:
            where = {"generation": "here (looks vary at export: teleop export --vary)",
                     "export": "here (physics varies when episodes are made: teleop generate|run|serve --vary)",
                     "eval": "here"}[stage]
            known = ", ".join((*groups, *allowed))
            if word in GROUPS or word in PHYSICS_KINDS + LOOKS_KINDS:
                raise VariationError(f"--vary {word!r} does not apply {where}; words: {known}")
            raise VariationError(f"--vary: unknown word {word!r} (words: {known})")
    return tuple(dict.fromkeys(out))


def physics_kinds(kinds: Sequence[str]) -> tuple[str, ...]:
    return tuple(k for k in kinds if k in PHYSICS_KINDS)


def looks_kinds(kinds: Sequence[str], stage: str) -> tuple[str, ...]:
    """The looks among `kinds`; in evaluation `distractors` are physical (the scene is simulated), not a look."""
    return tuple(k for k in kinds if k in LOOKS_KINDS and not (stage == "eval" and k == "distractors"))


@dataclass(frozen=True)
class Variation:
    """A request to vary: which kinds, range overrides (over the task's own), texture images, and the seed split.

    looks_seed: the first look seed (export: variant j uses looks_seed + j, a training seed;
    eval: held-out seeds are HELD_OUT_BASE + looks_seed).
    """

    kinds: tuple[str, ...] = ()
    overrides: Mapping[str, Any] = field(default_factory=dict)
    texture_files: tuple[tuple[str, bytes], ...] = field(default=(), repr=False)
    split: str = "train"
    looks_seed: int = 0

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise VariationError(f"variation split {self.split!r}: choose {' or '.join(SPLITS)}")
        if isinstance(self.looks_seed, bool) or not isinstance(self.looks_seed, int) or not 0 <= self.looks_seed < HELD_OUT_BASE:
            raise VariationError(f"--looks-seed {self.looks_seed!r}: expected a whole number 0..{HELD_OUT_BASE - 1}")

    @property
    def physics(self) -> tuple[str, ...]:
        return physics_kinds(self.kinds)

    def ranges(self, task_ranges: Ranges | None) -> Ranges:
        """The task's ranges (or the defaults) with this request's overrides and texture images."""
        ranges = parse_ranges(dict(self.overrides), "--vary-range", task_ranges or DEFAULT_RANGES)
        if self.texture_files:
            ranges = replace(ranges, texture_files=ranges.texture_files + self.texture_files)
        return ranges

    def to_json(self) -> dict[str, Any]:
        return {"kinds": list(self.kinds), "overrides": dict(self.overrides), "texture_files": [n for n, _ in self.texture_files],
                "split": self.split, "looks_seed": self.looks_seed}


def task_ranges(task: Any) -> Ranges | None:
    """The ranges a task declares (a task file's `[variation]` table), or None."""
    return getattr(task, "variation", None)


def physics_rng(seed: int, split: str = "train") -> np.random.Generator:
    """The physics draws of scene seed `seed`: the same seed, the same parameters; held-out draws apart."""
    return np.random.default_rng([PHYSICS_STREAM, SPLITS.index(split), int(seed)])


def training_look_seed(looks_seed: int, variant: int) -> int:
    """Variant `variant`'s look seed at export; VariationError when it would reach the held-out range."""
    seed = int(looks_seed) + int(variant)
    if not 0 <= seed < HELD_OUT_BASE:
        raise VariationError(f"--looks-seed {looks_seed} with {variant + 1} looks reaches the held-out seeds "
                             f"(training looks seeds are 0..{HELD_OUT_BASE - 1})")
    return seed


def eval_look_seed(looks_seed: int, split: str) -> int:
    """The look seed `teleop eval --looks-seed S` uses: held out (HELD_OUT_BASE + S) unless asked for training looks."""
    return HELD_OUT_BASE + int(looks_seed) if split == "held_out" else int(looks_seed)


def looks_rng(look_seed: int, scene_seed: int) -> np.random.Generator:
    """The draws of one look of one episode: the same (look seed, scene seed), the same look."""
    return np.random.default_rng([LOOKS_STREAM, int(look_seed), int(scene_seed) & 0xFFFFFFFF])


def uniform(rng: np.random.Generator, pair: tuple[float, float]) -> float:
    lo, hi = pair
    return float(lo) if lo == hi else float(rng.uniform(lo, hi))


def count(rng: np.random.Generator, pair: tuple[int, int]) -> int:
    lo, hi = pair
    return int(lo) if lo == hi else int(rng.integers(lo, hi + 1))


__all__ = [
    "DEFAULT_RANGES", "DISTRACTOR_PREFIX", "GROUPS", "HELD_OUT_BASE", "KEYS", "LOOKS_KINDS", "PHYSICS_KINDS", "Ranges",
    "VARIATION_KEY", "Variation", "VariationError", "eval_look_seed", "looks_kinds", "looks_rng", "parse_range_flags",
    "parse_ranges", "parse_vary", "physics_kinds", "physics_rng", "read_texture", "task_ranges", "training_look_seed",
]
