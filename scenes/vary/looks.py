"""Looks variation: another look of a recorded model, for rendering only (physics and recorded states untouched).

`sample_looks` draws a look from a compiled model as JSON (what the dataset's episode
metadata stores); `apply_looks` makes the model that renders it from the recorded XML:
lights replaced, colours and textures of the table, floor and task objects, camera
jitter, visual-only distractor geoms. No body or joint is added, so the recorded
states restore into it unchanged. Each kind draws from a generator of its own
(scenes.vary.variation.looks_rng + the kind), so turning one kind on or off never changes
another's draws. Lengths are metres, angles degrees, colours rgb(a) in 0..1.
"""

from __future__ import annotations

import colorsys
import math
from collections.abc import Collection, Mapping, Sequence
from typing import Any

import mujoco
import numpy as np

from scenes.vary import distractors
from scenes.assembly.arena import TABLE_TOP
from scenes.errors import first_line
from scenes.cameras.extra import ExtraCamera
from scenes.vary.textures import PROCEDURAL, TEXTURE_SIZE, procedural
from scenes.vary.variation import LOOKS_KINDS, LOOKS_STREAM, Ranges, VariationError, count, uniform

TABLE_MATERIAL, FLOOR_MATERIAL = "table", "floor"
OBJECT_TEXTURE_CHANCE = 0.5  # share of objects that get a (grey, low-contrast) texture under their colour
TEXTURE_REPEAT = {"table": 3.0, "floor": 1.5}  # tiles per metre (texuniform)


def kind_rng(look_seed: int, scene_seed: int, kind: str) -> np.random.Generator:
    """One kind's draws for one look of one episode."""
    return np.random.default_rng([LOOKS_STREAM, int(look_seed), int(scene_seed) & 0xFFFFFFFF, LOOKS_KINDS.index(kind)])


def robot_roots(model: mujoco.MjModel, robot_joints: Sequence[str]) -> set[int]:
    """The root bodies (the world's children) that carry the robots' joints."""
    return {int(model.body_rootid[model.jnt_bodyid[model.joint(j).id]]) for j in robot_joints}


def object_roots(model: mujoco.MjModel, robots: Collection[int]) -> list[int]:
    """The world's children that are not a robot's: task objects (and physical distractors), by body id."""
    return sorted({int(model.body_rootid[b]) for b in range(1, model.nbody)} - set(robots))


def _key(model: mujoco.MjModel, body: int) -> str:
    return model.body(body).name or f"#{body}"


def _body(model: mujoco.MjModel, key: str) -> int:
    return int(key[1:]) if key.startswith("#") else model.body(key).id


def _material_rgb(model: mujoco.MjModel, name: str) -> list[float] | None:
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, name)
    return [float(v) for v in model.mat_rgba[i][:3]] if i >= 0 else None


def _hsv(rgb: Sequence[float], dh: float, value: float) -> list[float]:
    h, s, v = colorsys.rgb_to_hsv(*[float(c) for c in rgb[:3]])
    r, g, b = colorsys.hsv_to_rgb((h + dh) % 1.0, s, min(1.0, v * value))
    return [r, g, b]


def _round(values: Sequence[float], digits: int = 4) -> list[float]:
    return [round(float(v), digits) for v in values]


def _sample_lights(rng: np.random.Generator, model: mujoco.MjModel, ranges: Ranges) -> dict[str, Any]:
    cx, cy = (float(v) for v in model.stat.center[:2])
    lights = []
    for _ in range(count(rng, ranges.lights)):
        pos = np.array([cx + rng.uniform(-1, 1) * ranges.light_spread, cy + rng.uniform(-1, 1) * ranges.light_spread,
                        TABLE_TOP + uniform(rng, ranges.light_height)])
        aim = np.array([cx + rng.uniform(-0.2, 0.2), cy + rng.uniform(-0.2, 0.2), TABLE_TOP])
        direction = (aim - pos) / np.linalg.norm(aim - pos)
        level = uniform(rng, ranges.light_intensity)
        tint = np.array([1.0 + rng.uniform(-0.1, 0.1), 1.0, 1.0 + rng.uniform(-0.1, 0.1)])  # warm to cool
        lights.append({"pos": _round(pos), "dir": _round(direction), "diffuse": _round(np.clip(level * tint, 0, 1))})
    return {"headlight": round(float(rng.uniform(0.6, 1.1)), 4), "lights": lights}


def _sample_colors(rng: np.random.Generator, model: mujoco.MjModel, objects: list[int], ranges: Ranges) -> dict[str, Any]:
    h = float(rng.random())
    table = colorsys.hsv_to_rgb(h, uniform(rng, ranges.table_saturation), uniform(rng, ranges.table_value))
    per = {_key(model, b): {"hue": round(float(rng.uniform(-ranges.hue, ranges.hue)), 4),
                            "brightness": round(uniform(rng, ranges.brightness), 4)} for b in objects}
    return {"table": _round(table), "objects": per}


def _texture_source(rng: np.random.Generator, ranges: Ranges, files: bool) -> str:
    sources = list(ranges.textures) + ([name for name, _ in ranges.texture_files] if files else [])
    if not sources:
        return ""
    return sources[int(rng.integers(len(sources)))]


def _sample_textures(rng: np.random.Generator, model: mujoco.MjModel, objects: list[int], ranges: Ranges) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for surface in ("table", "floor"):
        source = _texture_source(rng, ranges, files=True)
        shade = [round(float(rng.uniform(0.55, 0.8)), 4), round(float(rng.uniform(1.0, 1.3)), 4)]  # the two colours' shades
        floor = colorsys.hsv_to_rgb(float(rng.random()), float(rng.uniform(0.0, 0.3)), float(rng.uniform(0.25, 0.55)))
        seed = int(rng.integers(2**31))
        if source:
            out[surface] = {"source": source, "seed": seed, "shades": shade}
            if surface == "floor":
                out[surface]["rgb"] = _round(floor)
    objs = {}
    for b in objects:
        source = _texture_source(rng, ranges, files=False)
        chosen = float(rng.random()) < OBJECT_TEXTURE_CHANCE
        seed = int(rng.integers(2**31))
        if source and chosen:
            objs[_key(model, b)] = {"source": source, "seed": seed}
    out["objects"] = objs
    return out


def _sample_cameras(rng: np.random.Generator, model: mujoco.MjModel, ranges: Ranges) -> dict[str, Any]:
    out = {}
    for c in range(model.ncam):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        offset = direction * ranges.camera_pos * float(rng.random()) ** (1 / 3)  # uniform in the ball
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = float(rng.uniform(0.0, ranges.camera_angle))
        out[model.camera(c).name or f"#{c}"] = {"offset": _round(offset, 5), "axis": _round(axis), "angle_deg": round(angle, 4)}
    return out


def sample_looks(model: mujoco.MjModel, robot_joints: Sequence[str], ranges: Ranges, kinds: Sequence[str],
                 look_seed: int, scene_seed: int) -> dict[str, Any]:
    """One look of `model` (a recorded scene) as JSON: the same arguments, the same look."""
    objects = object_roots(model, robot_roots(model, robot_joints))
    look: dict[str, Any] = {"look_seed": int(look_seed), "scene_seed": int(scene_seed), "kinds": [k for k in LOOKS_KINDS if k in kinds]}
    for kind in look["kinds"]:
        rng = kind_rng(look_seed, scene_seed, kind)
        if kind == "lights":
            look[kind] = _sample_lights(rng, model, ranges)
        elif kind == "colors":
            look[kind] = _sample_colors(rng, model, objects, ranges)
        elif kind == "textures":
            look[kind] = _sample_textures(rng, model, objects, ranges)
        elif kind == "cameras":
            look[kind] = _sample_cameras(rng, model, ranges)
        else:  # distractors: visual only, clear of every object and base at the recorded start
            data = mujoco.MjData(model)
            mujoco.mj_kinematics(model, data)
            area = distractors.area_of(model)
            clear = distractors.obstacles(model, data, robot_roots(model, robot_joints), area.reach)
            look[kind] = distractors.sample(rng, ranges, area, clear)
    return look


# -- applying -------------------------------------------------------------------------------------------


def _texture_pixels(entry: Mapping[str, Any], rgb: Sequence[float], files: Mapping[str, bytes]) -> np.ndarray | bytes:
    """A texture's pixels (procedural: an array) or its PNG bytes (a file the user named)."""
    source = entry["source"]
    if source in PROCEDURAL:
        lo, hi = entry.get("shades", [0.7, 1.0])
        return procedural(source, entry["seed"], np.clip(np.asarray(rgb) * lo, 0, 1), np.clip(np.asarray(rgb) * hi, 0, 1))
    if source not in files:
        raise VariationError(f"texture file {source!r} is not among the texture files given (--texture FILE, or the task's "
                             "[variation] texture_files)")
    return files[source]


def _add_texture(spec: mujoco.MjSpec, name: str, pixels: np.ndarray | bytes) -> None:
    if isinstance(pixels, bytes):
        file = f"{name}.png"
        spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, file=file)
        spec.assets = {**spec.assets, file: pixels}
        return
    tex = spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, width=pixels.shape[1], height=pixels.shape[0], nchannel=3)
    tex.data = np.ascontiguousarray(pixels, dtype=np.uint8).tobytes()


def _textured_material(spec: mujoco.MjSpec, material: str, texture: str, repeat: float) -> None:
    mat = spec.material(material)
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = texture
    mat.texuniform = True
    mat.texrepeat = [repeat, repeat]
    mat.rgba = [1.0, 1.0, 1.0, 1.0]  # the colours are in the texture


def _quat_about(axis: Sequence[float], degrees: float) -> np.ndarray:
    half = math.radians(degrees) / 2
    return np.array([math.cos(half), *(np.asarray(axis, float) * math.sin(half))])


def apply_looks(xml: str, assets: Mapping[str, bytes], look: Mapping[str, Any], files: Mapping[str, bytes] | None = None,
                cameras: Sequence[ExtraCamera] = ()) -> mujoco.MjModel:
    """The model that renders `look` of the recorded `xml`: only what rendering reads differs from the recorded model.

    files: texture images by name (PNG bytes) a look may name; cameras: fixed cameras added to the recording
    (scenes.cameras.extra), jittered like its own. VariationError (one line) when it cannot be built.
    """
    files = dict(files or {})
    spec = mujoco.MjSpec.from_string(xml, assets=dict(assets))
    for cam in cameras:
        cam.pose.add_to(spec.worldbody, cam.name)
    base = spec.compile()  # names and colours as recorded
    lights = look.get("lights")
    if lights is not None:
        for light in list(spec.worldbody.lights):
            spec.delete(light)
        for i, light in enumerate(lights["lights"]):
            spec.worldbody.add_light(name=f"look_light{i}", pos=light["pos"], dir=light["dir"], diffuse=light["diffuse"],
                                     specular=[0.05, 0.05, 0.05], castshadow=False)
        level = float(lights["headlight"])
        spec.visual.headlight.ambient = list(np.asarray(spec.visual.headlight.ambient) * level)
        spec.visual.headlight.diffuse = list(np.asarray(spec.visual.headlight.diffuse) * level)
    colors = look.get("colors")
    table_rgb = colors["table"] if colors is not None else _material_rgb(base, TABLE_MATERIAL)
    if colors is not None and _material_rgb(base, TABLE_MATERIAL) is not None:
        spec.material(TABLE_MATERIAL).rgba = [*table_rgb, 1.0]
    textures = look.get("textures")
    if textures is not None:
        for surface, material in (("table", TABLE_MATERIAL), ("floor", FLOOR_MATERIAL)):
            entry = textures.get(surface)
            base_rgb = table_rgb if surface == "table" else entry.get("rgb")
            if entry is None or _material_rgb(base, material) is None:
                continue
            _add_texture(spec, f"look_{surface}", _texture_pixels(entry, base_rgb or [0.6, 0.5, 0.4], files))
            _textured_material(spec, material, f"look_{surface}", TEXTURE_REPEAT[surface])
        for key, entry in textures.get("objects", {}).items():
            body = base.body(_body(base, key)).name
            if not body:
                continue  # an unnamed body cannot be found in the spec
            pixels = procedural(entry["source"], entry["seed"], [0.72, 0.72, 0.72], [1.0, 1.0, 1.0], TEXTURE_SIZE // 2)
            name = f"look_obj_{_body(base, key)}"
            _add_texture(spec, name, pixels)
            mat = spec.add_material(name=name)
            mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name
            mat.texuniform = True
            mat.texrepeat = [40.0, 40.0]
            for geom in spec.body(body).find_all(mujoco.mjtObj.mjOBJ_GEOM):
                geom.material = name  # the geom's own rgba still colours it: the texture shades it
    for d in look.get("distractors") or []:
        distractors.add(spec, d, physical=False)
    try:
        model = spec.compile()
    except ValueError as exc:
        raise VariationError(f"the look does not compile: {first_line(exc)}") from None
    if colors is not None:
        for key, change in colors["objects"].items():
            root = _body(base, key)
            for g in np.flatnonzero(model.body_rootid[model.geom_bodyid] == root):
                rgba = model.geom_rgba[g]
                rgba[:3] = _hsv(rgba[:3], change["hue"], change["brightness"])
    for name, jitter in (look.get("cameras") or {}).items():
        c = int(name[1:]) if name.startswith("#") else model.camera(name).id
        model.cam_pos[c] = model.cam_pos[c] + np.asarray(jitter["offset"])
        quat = np.empty(4)
        mujoco.mju_mulQuat(quat, model.cam_quat[c], _quat_about(jitter["axis"], jitter["angle_deg"]))
        model.cam_quat[c] = quat
    return model


__all__ = ["apply_looks", "object_roots", "robot_roots", "sample_looks"]
