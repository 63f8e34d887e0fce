"""The camera figure of a built scene: how many pixels across its smallest task object is, per camera.

`object_px_at_96` is what an image policy at 96x96 gets to see of the objects it
must act on: the smallest projected width (px) among the task's objects at their
start pose (seed's placement, robot at home), per camera, occlusion ignored.
"""

from __future__ import annotations

import mujoco

from scenes.assembly.build import Scene
from scenes.cameras.view import FIGURE_SIZE, object_px


def object_bodies(scene: Scene) -> list[int]:
    """Body ids of the task's objects (a task file's [[object]]s; an mjcf object by its root body)."""
    task = scene.task
    aliases = getattr(task, "aliases", {}) or {}
    out = []
    for obj in getattr(task, "objects", None) or []:
        for name in (obj.name, aliases.get(obj.name)):
            bid = mujoco.mj_name2id(scene.model, mujoco.mjtObj.mjOBJ_BODY, name) if name else -1
            if bid >= 0:
                out.append(bid)
                break
    return out


def camera_figures(scene: Scene, size: int = FIGURE_SIZE) -> dict[str, float]:
    """camera name -> the smallest task object's projected width (px) at size x size, at the scene's start."""
    data = scene.make_data()  # reset: objects where the seed put them, arms at home, mj_forward done
    bodies = object_bodies(scene)
    return {name: round(object_px(scene.model, data, i, bodies, size), 2) for i, name in enumerate(scene.cameras)}
