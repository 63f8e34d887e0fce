"""Perception beside the truth: each object's estimate, its true position (read from the state only to score
the estimate) and the error; what `teleop perceive` prints and the bench measures."""

from __future__ import annotations

import mujoco
import numpy as np

from teleop.instruct.perceive import Perception, RgbdCamera, perceive, scene_objects


def compared(controller, camera: str = "front", width: int = 224, height: int = 224,
             rgbd: RgbdCamera | None = None) -> tuple[Perception, list[dict]]:
    """(the perception of `controller`'s scene now, one row per object: name, estimated, true, error_m, visible, ...)."""
    own = rgbd is None
    rgbd = RgbdCamera(controller.model, width, height) if own else rgbd
    try:
        seen = perceive(rgbd, controller.model, controller.data, scene_objects(controller.scene.task), camera)
    finally:
        if own:
            rgbd.close()
    rows = []
    for name, est in seen.estimates.items():
        bid = mujoco.mj_name2id(controller.model, mujoco.mjtObj.mjOBJ_BODY, name)
        true = controller.data.xpos[bid] if bid >= 0 else None
        error = None if est.position is None or true is None else float(np.linalg.norm(est.position - true))
        rows.append({
            "name": name,
            "estimated": None if est.position is None else [round(float(v), 4) for v in est.position],
            "true": None if true is None else [round(float(v), 4) for v in true],
            "error_m": None if error is None else round(error, 4),
            "visible": est.visible,
            "status": est.status,
            "top_z": None if est.top_z is None else round(est.top_z, 4),
            "yaw": None if est.yaw is None else round(est.yaw, 3),
            "pixels": est.pixels,
            "occluded_fraction": est.occluded_fraction,
        })
    return seen, rows
