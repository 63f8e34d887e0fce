"""Tasks: the objects on the table, where a seed puts them, and what success means.

A task adds its bodies to the arena spec (so the compiled model is one honest
MJCF, no string pasting) and judges success from MjData alone, so that a
recording can be judged again at replay.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np

from scenes.arena import TABLE_TOP, Layout

CUBE_RGBA = ([0.85, 0.2, 0.15, 1.0], [0.15, 0.45, 0.85, 1.0])


def _add_cube(spec: mujoco.MjSpec, name: str, pos, size: float, rgba) -> None:
    body = spec.worldbody.add_body(name=name, pos=list(pos))
    body.add_freejoint(name=f"{name}_joint")
    body.add_geom(
        name=f"{name}_geom", type=mujoco.mjtGeom.mjGEOM_BOX, size=[size] * 3, rgba=rgba,
        density=600.0, friction=[1.2, 0.01, 0.0005], condim=4,
    )


def _body_pos(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> np.ndarray:
    return data.xpos[model.body(name).id]


SubtaskKind = Literal["grasp", "place", "push"]


@dataclass(frozen=True)
class SubtaskSpec:
    """One object-centric subtask of a task (MimicGen's unit of generation).

    object: the body, site or geom whose frame the subtask's motion is relative to.
    kind: how its end is found in a recording: "grasp" ends when the gripper
        closes on the object, "place" when it opens again, "push" runs to the
        episode's end (no gripper event).
    """

    object: str
    kind: SubtaskKind


def object_pose(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), rotation matrix (3, 3)) of a body, site or geom in the world frame (m)."""
    for kind, pos, mat in ((mujoco.mjtObj.mjOBJ_BODY, data.xpos, data.xmat), (mujoco.mjtObj.mjOBJ_SITE, data.site_xpos, data.site_xmat),
                           (mujoco.mjtObj.mjOBJ_GEOM, data.geom_xpos, data.geom_xmat)):
        i = mujoco.mj_name2id(model, kind, name)
        if i >= 0:
            return pos[i].copy(), mat[i].reshape(3, 3).copy()
    raise KeyError(f"the scene has no body, site or geom named {name!r}")


@dataclass
class Task:
    """Base task: subclasses add objects, judge success and name their subtasks in order."""

    name: str = ""
    summary: str = ""
    text: str = ""
    needs_bimanual: bool = False
    allows_bimanual: bool = False
    subtasks: tuple[SubtaskSpec, ...] = ()

    def supports(self, bimanual: bool) -> bool:
        return self.allows_bimanual if bimanual else not self.needs_bimanual

    def build(self, spec: mujoco.MjSpec, layout: Layout, rng: np.random.Generator) -> None:
        raise NotImplementedError

    def success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        raise NotImplementedError

    @staticmethod
    def place(layout: Layout, rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
        """A random (x, y) in the workspace, seeded."""
        offset = rng.uniform(-1.0, 1.0, size=2) * layout.spread * scale
        return np.array(layout.center) + offset


class Lift(Task):
    def __init__(self) -> None:
        super().__init__("lift", "pick up the cube and lift it 5 cm", "Pick up the red cube and lift it.", allows_bimanual=True,
                         subtasks=(SubtaskSpec("cube", "grasp"),))

    def build(self, spec, layout, rng):
        xy = self.place(layout, rng)
        _add_cube(spec, "cube", (*xy, TABLE_TOP + layout.size), layout.size, CUBE_RGBA[0])

    def success(self, model, data):
        return bool(_body_pos(model, data, "cube")[2] > TABLE_TOP + model.geom("cube_geom").size[0] + 0.05)


class Stack(Task):
    def __init__(self) -> None:
        super().__init__("stack", "put the red cube on the blue cube", "Stack the red cube on the blue cube.",
                         subtasks=(SubtaskSpec("cube", "grasp"), SubtaskSpec("cube_base", "place")))

    def build(self, spec, layout, rng):
        a = self.place(layout, rng)
        for _ in range(100):  # keep the cubes apart so neither starts on the other
            b = self.place(layout, rng)
            if np.linalg.norm(a - b) > 5 * layout.size:
                break
        _add_cube(spec, "cube", (*a, TABLE_TOP + layout.size), layout.size, CUBE_RGBA[0])
        _add_cube(spec, "cube_base", (*b, TABLE_TOP + layout.size), layout.size, CUBE_RGBA[1])

    def success(self, model, data):
        size = model.geom("cube_geom").size[0]
        top, base = _body_pos(model, data, "cube"), _body_pos(model, data, "cube_base")
        on_top = np.linalg.norm(top[:2] - base[:2]) < size and abs(top[2] - base[2] - 2 * size) < 0.25 * size
        base_down = base[2] < TABLE_TOP + 1.2 * size
        still = np.linalg.norm(data.qvel[model.joint("cube_joint").dofadr[0]:][:3]) < 0.05
        return bool(on_top and base_down and still)


class PickPlace(Task):
    def __init__(self) -> None:
        super().__init__("pick_place", "put the cube into the bin", "Put the red cube into the grey bin.",
                         subtasks=(SubtaskSpec("cube", "grasp"), SubtaskSpec("bin", "place")))

    def build(self, spec, layout, rng):
        s = layout.size
        cube_xy = self.place(layout, rng)
        bin_xy = np.array(layout.center) + np.array([0.0, -np.sign(cube_xy[1] - layout.center[1] + 1e-9) * 1.6 * layout.spread])
        bin_xy[0] += rng.uniform(-0.3, 0.3) * layout.spread
        _add_cube(spec, "cube", (*cube_xy, TABLE_TOP + s), s, CUBE_RGBA[0])
        half = 3.0 * s  # inner half-width of the bin
        wall, height = 0.004, 2.2 * s
        body = spec.worldbody.add_body(name="bin", pos=[*bin_xy, TABLE_TOP])
        grey = [0.55, 0.57, 0.6, 1.0]
        body.add_geom(name="bin_floor", type=mujoco.mjtGeom.mjGEOM_BOX, size=[half + wall, half + wall, wall], pos=[0, 0, wall], rgba=grey)
        for i, (dx, dy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
            size = [wall, half + wall, height / 2] if dx else [half + wall, wall, height / 2]
            body.add_geom(name=f"bin_wall{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=size,
                          pos=[dx * (half + wall), dy * (half + wall), height / 2], rgba=grey)
        body.add_site(name="bin_center", pos=[0, 0, 0], size=[half, half, height / 2], type=mujoco.mjtGeom.mjGEOM_BOX, rgba=[0, 0, 0, 0])

    def success(self, model, data):
        cube = _body_pos(model, data, "cube")
        bin_pos = _body_pos(model, data, "bin")
        half = model.site("bin_center").size[0]
        inside = np.all(np.abs(cube[:2] - bin_pos[:2]) < half)
        low = cube[2] < bin_pos[2] + 2 * model.site("bin_center").size[2]
        return bool(inside and low)


class Door(Task):
    def __init__(self) -> None:
        super().__init__("door", "open the hinged door 30 degrees", "Open the door by its handle.",
                         subtasks=(SubtaskSpec("door_handle", "push"),))

    def build(self, spec, layout, rng):
        s = layout.size
        width, height, thick = 10 * s, 12 * s, 0.012
        xy = np.array(layout.center) + np.array([layout.spread * (0.9 + 0.3 * rng.uniform()), rng.uniform(-0.5, 0.5) * layout.spread])
        frame = spec.worldbody.add_body(name="door_frame", pos=[*xy, TABLE_TOP])
        grey = [0.4, 0.42, 0.45, 1.0]
        frame.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.015, 0.015, height / 2], pos=[0, -width / 2 - 0.02, height / 2], rgba=grey)
        frame.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.015, 0.015, height / 2], pos=[0, width / 2 + 0.02, height / 2], rgba=grey)
        # The hinge is on the +y post; the door swings toward the robot (-x).
        door = frame.add_body(name="door", pos=[0, width / 2, 0])
        door.add_joint(name="door_hinge", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], range=[0, 1.9], damping=0.5,
                       frictionloss=0.05, armature=0.01)
        door.add_geom(name="door_panel", type=mujoco.mjtGeom.mjGEOM_BOX, size=[thick / 2, width / 2, height / 2 - 0.005],
                      pos=[0, -width / 2, height / 2 + 0.002], rgba=[0.7, 0.55, 0.35, 1.0], density=400)
        handle_r = 0.45 * s
        door.add_geom(name="door_handle", type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[min(0.012, handle_r), 1.6 * s],
                      pos=[-thick / 2 - 2.2 * s, -width + 2.5 * s, height * 0.55], rgba=[0.8, 0.8, 0.82, 1.0], density=800,
                      friction=[1.2, 0.01, 0.0005], condim=4)
        for dz in (-1, 1):
            door.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[1.1 * s, 0.006, 0.006],
                          pos=[-thick / 2 - 1.1 * s, -width + 2.5 * s, height * 0.55 + dz * 1.2 * s], rgba=[0.8, 0.8, 0.82, 1.0])
        door.add_site(name="door_handle_site", pos=[-thick / 2 - 2.2 * s, -width + 2.5 * s, height * 0.55], size=[0.005] * 3)

    def success(self, model, data):
        return bool(data.qpos[model.joint("door_hinge").qposadr[0]] > np.deg2rad(30))


class Handover(Task):
    def __init__(self) -> None:
        super().__init__("handover", "pass the cube from the left arm to the right arm",
                         "Pick up the cube with the left arm and hand it to the right arm.", needs_bimanual=True, allows_bimanual=True)

    def build(self, spec, layout, rng):
        xy = np.array(layout.center) + np.array([-0.6, 0.0]) * layout.spread * 2 + rng.uniform(-0.3, 0.3, 2) * layout.spread
        _add_cube(spec, "cube", (*xy, TABLE_TOP + layout.size), layout.size, CUBE_RGBA[0])

    def success(self, model, data):
        cube = _body_pos(model, data, "cube")
        right_ee = data.site_xpos[model.site("right/ee_site").id]
        size = model.geom("cube_geom").size[0]
        held_by_right = np.linalg.norm(cube - right_ee) < 1.5 * size
        return bool(held_by_right and cube[2] > TABLE_TOP + size + 0.03)


TASKS: dict[str, Task] = {t.name: t for t in (Lift(), Stack(), PickPlace(), Door(), Handover())}
