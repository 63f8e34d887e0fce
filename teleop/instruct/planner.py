"""Atomic actions and object positions into a script of the existing engine (devices/script.py).

Positions come from the camera (teleop.instruct.perceive) or, for comparison, from the
simulator's state (`state_positions`); either way the script aims at absolute world points
(`to`, m) with the hand turned to the object's yaw (`orient`, rad), so the episode is what the
plan said, not what the state held. Heights follow the library's scripts: grasp halfway up
the object (between its top and the table), approach 12 cm above, carry 15 cm up, release an object 1.2 cm above the top
it goes on (`in` a bin: above its rim), push a third of the way up from 5 cm behind the object's near face.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from devices.script import ScriptStep, heading, parse_script
from scenes.assembly.arena import TABLE_TOP
from teleop.instruct.grammar import Action, GroundingError
from teleop.instruct.perceive import Estimate, Perception

APPROACH_M = 0.12  # above a grasp or a release point
CARRY_M = 0.15  # lift after a grasp
CLEARANCE_M = 0.012  # between a carried object's bottom and the top it is put on
PUSH_STANDOFF_M = 0.05  # behind the near face of a pushed object
PUSH_HEIGHT = 0.35  # of the pushed object's height: where the closed fingers meet it


@dataclass(frozen=True)
class Located:
    """Where the planner believes an object is (world, m and rad)."""

    name: str
    position: np.ndarray
    top_z: float
    yaw: float | None = None
    half_extent: float = 0.02

    @property
    def middle(self) -> float:
        """Halfway up the object (m, world z): where a grasp or a push aims, whatever its origin's convention."""
        return (self.top_z + TABLE_TOP) / 2

    def as_json(self) -> dict:
        out = {"position": [round(float(v), 4) for v in self.position], "top_z": round(self.top_z, 4)}
        if self.yaw is not None:
            out["yaw"] = round(self.yaw, 3)
        return out


def from_perception(perception: Perception, wanted: Sequence[str]) -> dict[str, Located]:
    """The perceived objects the plan needs; one the camera did not see is one line (not guessed)."""
    out = {}
    for name in wanted:
        est: Estimate = perception.estimates[name]
        if est.position is None:
            raise GroundingError(f"the camera '{perception.camera}' cannot see the {name} (occluded or out of view): "
                                 "try another --instruct-camera or --instruct-state")
        out[name] = Located(name, est.position, float(est.top_z), est.yaw, float(est.half_extent or 0.02))
    return out


def state_positions(model: mujoco.MjModel, data: mujoco.MjData, names: Sequence[str]) -> dict[str, Located]:
    """The same facts read from the simulator's state (`--instruct-state`): body position, its geoms' top, yaw."""
    out = {}
    for name in names:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            raise GroundingError(f"no body '{name}' in the scene")
        top, half = TABLE_TOP, 0.0
        for g in np.flatnonzero(model.geom_bodyid == bid):
            rot = data.geom_xmat[g].reshape(3, 3)
            centre = data.geom_xpos[g] + rot @ model.geom_aabb[g, :3]
            reach = np.abs(rot) @ model.geom_aabb[g, 3:]
            top = max(top, float(centre[2] + reach[2]))
            half = max(half, float(max(reach[0], reach[1])))
        yaw = heading(data.xquat[bid])
        yaw = (yaw + math.pi / 2) % math.pi - math.pi / 2
        out[name] = Located(name, data.xpos[bid].copy(), top, yaw, half or 0.02)
    return out


def grasp_yaw(yaw: float | None) -> float:
    """The hand's heading for an object's yaw: the nearest to the hand's start (0) of yaw + k pi/2 for a box."""
    if yaw is None:
        return 0.0
    return (yaw + math.pi / 4) % (math.pi / 2) - math.pi / 4


def plan_steps(actions: Sequence[Action], where: dict[str, Located], home: np.ndarray) -> list[dict]:
    """The script steps (JSON objects, as in scenes/scripts) that carry out `actions`."""
    steps: list[dict] = []
    held: str | None = None

    def r(v) -> list[float]:
        return [round(float(x), 5) for x in v]

    def pick(name: str) -> None:
        o = where[name]
        x, y = o.position[:2]
        z = o.middle
        orient = [math.pi, 0.0, round(grasp_yaw(o.yaw), 5)]
        steps.extend([
            {"duration": 1.5, "to": r([x, y, z + APPROACH_M]), "orient": orient, "gripper": "open"},
            {"duration": 1.0, "to": r([x, y, z])},
            {"duration": 0.6, "gripper": "close"},
            {"duration": 1.0, "move": [0, 0, CARRY_M]},
        ])

    for act in actions:
        if act.kind == "pick":
            if held == act.obj:
                continue  # "pick up the cube and lift it": it is up already
            pick(act.obj)
            held = act.obj
        elif act.kind == "place":
            if held != act.obj:
                pick(act.obj)
            o, t = where[act.obj], where[act.target]
            half_height = max(o.top_z - o.middle, 0.005)
            z = t.top_z + half_height + CLEARANCE_M
            tx, ty = t.position[:2]
            steps.extend([
                {"duration": 1.5, "to": r([tx, ty, z + 0.1])},
                {"duration": 1.0, "to": r([tx, ty, z])},
                {"duration": 0.6, "gripper": "open"},
                {"duration": 0.8, "move": [0, 0, 0.1]},
            ])
            held = None
        elif act.kind == "push":
            o, t = where[act.obj], where[act.target]
            d = t.position[:2] - o.position[:2]
            norm = float(np.linalg.norm(d))
            if norm < 1e-6:
                raise GroundingError(f"the {act.obj} is on the {act.target} already")
            d = d / norm
            pz = TABLE_TOP + PUSH_HEIGHT * (o.top_z - TABLE_TOP)  # low enough not to tip a tall object over
            start = o.position[:2] - d * (o.half_extent + PUSH_STANDOFF_M)
            end = t.position[:2] - d * (o.half_extent + 0.015)
            steps.extend([
                {"duration": 0.5, "gripper": "close"},
                {"duration": 1.5, "to": r([*start, pz + 0.08])},
                {"duration": 0.8, "to": r([*start, pz])},
                {"duration": 2.5, "to": r([*end, pz])},
                {"duration": 0.8, "move": r([*(-0.03 * d), 0.1])},
            ])
        elif act.kind in ("open", "close"):
            steps.append({"duration": 0.6, "gripper": act.kind})
            held = None if act.kind == "open" else held
        elif act.kind == "home":
            steps.append({"duration": 1.5, "to": r(home), "orient": [math.pi, 0.0, 0.0]})
    steps.append({"duration": 0.5})
    return steps


def checked(steps: list[dict], name: str) -> list[ScriptStep]:
    """The steps validated exactly as a script file is (ScriptError naming the step and field)."""
    return parse_script(json.dumps({"steps": steps}), name)
