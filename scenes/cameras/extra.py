"""Cameras added after the fact: `NAME=pos:x,y,z;look_at:x,y,z[;fovy:deg]`, put into a recorded model.

A recording embeds its model XML, so a camera added at export goes into that
model (compiled again with the one extra camera: nothing the physics reads
changes) and renders the recorded states. Positions are metres in the world
frame: the (first) robot's base at the origin facing +x, the table top at z = 0.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import mujoco

from scenes.cameras.view import CameraPose, look_at_axes
from scenes.errors import TeleopError, first_line
from scenes.numbers import number_or_nan

SYNTAX = "NAME=pos:x,y,z;look_at:x,y,z[;fovy:deg]"
NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
DEFAULT_FOVY = 45.0  # deg, MuJoCo's own default


class CameraSpecError(TeleopError, ValueError):
    """A camera given as text that cannot be used; one line naming the text and what is wrong."""


@dataclass(frozen=True)
class ExtraCamera:
    """A fixed camera to add to a model: its name and pose (m, world frame; fovy in degrees)."""

    name: str
    pose: CameraPose


def _vector(text: str, key: str, spec: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise CameraSpecError(f"camera {spec!r}: {key}: expected three numbers x,y,z (m), got {text!r}")
    return values  # type: ignore[return-value]


def parse_camera(spec: str) -> ExtraCamera:
    """`NAME=pos:x,y,z;look_at:x,y,z[;fovy:deg]` -> an ExtraCamera; CameraSpecError (one line) if malformed."""
    name, eq, rest = spec.partition("=")
    name = name.strip()
    if not eq or not NAME.match(name):
        raise CameraSpecError(f"camera {spec!r}: expected {SYNTAX} with NAME a letter or _ then letters, digits, _")
    fields: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in rest.split(";"))):
        key, colon, value = part.partition(":")
        key = key.strip()
        if not colon or key not in ("pos", "look_at", "fovy"):
            raise CameraSpecError(f"camera {spec!r}: unknown part {part!r} (expected {SYNTAX})")
        if key in fields:
            raise CameraSpecError(f"camera {spec!r}: {key} given twice")
        fields[key] = value.strip()
    missing = [k for k in ("pos", "look_at") if k not in fields]
    if missing:
        raise CameraSpecError(f"camera {spec!r}: {missing[0]} missing (expected {SYNTAX})")
    eye, target = _vector(fields["pos"], "pos", spec), _vector(fields["look_at"], "look_at", spec)
    fovy = DEFAULT_FOVY
    if "fovy" in fields:
        fovy = number_or_nan(fields["fovy"])
        if not 0.0 < fovy < 180.0:
            raise CameraSpecError(f"camera {spec!r}: fovy: expected degrees between 0 and 180, got {fields['fovy']!r}")
    try:
        right, up, _ = look_at_axes(eye, target)
    except ValueError:
        raise CameraSpecError(f"camera {spec!r}: look_at is the camera's own position") from None
    return ExtraCamera(name, CameraPose(pos=eye, xyaxes=(*map(float, right), *map(float, up)), fovy=fovy))


def parse_cameras(specs: Sequence[str]) -> list[ExtraCamera]:
    """Every spec parsed, names unique."""
    cameras = [parse_camera(s) for s in specs]
    names = [c.name for c in cameras]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise CameraSpecError(f"camera {twice[0]!r} is given twice")
    return cameras


def model_with_cameras(xml: str, assets: Mapping[str, bytes], cameras: Sequence[ExtraCamera]) -> mujoco.MjModel:
    """The model of `xml` (with its asset files) plus `cameras` in its world body.

    A name the model already has is a CameraSpecError: a recording keeps its own cameras.
    """
    spec = mujoco.MjSpec.from_string(xml, assets=dict(assets))
    have = {c.name for c in spec.cameras}
    for cam in cameras:
        if cam.name in have:
            raise CameraSpecError(f"camera {cam.name!r}: the model already has a camera of that name (recordings keep "
                                  "their own cameras; choose another name)")
        cam.pose.add_to(spec.worldbody, cam.name)
    try:
        return spec.compile()
    except Exception as exc:  # noqa: BLE001 - mujoco raises ValueError with a multi-line message
        raise CameraSpecError(f"the model does not compile with the added cameras: {first_line(exc)}") from None
