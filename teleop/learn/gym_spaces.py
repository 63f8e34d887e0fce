"""Bounds of the Gymnasium spaces of a scene, in the export's vector layouts.

Each vector is laid out as the LeRobot export lays it out (replay/features.py:
arms in recorded order, then concatenated); this module only says how far each
entry can go, in its own units:

  joints           rad (or m): the joint's range, a little wider for the
                   observed state (a servo overshoots a hard stop slightly);
                   unbounded for an unlimited joint
  gripper          1 = open .. 0 = closed: [0, 1] as an action; as a state,
                   wherever the fingers' travel maps on that scale
  EE position      m, world frame: a box around the arm's base
  quaternion wxyz  [-1, 1] each
  EE delta         m per tick and rad (rotation vector), world frame
  object poses     m and wxyz in the robot's base frame: within OBJECT_RANGE of the base
                   (an object knocked to the floor stays inside), quaternions [-1, 1]
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from gymnasium import spaces

from replay.features import ENV_STATE, ArmLayout, ObjectLayout, feature_key, features
from scenes.assembly.arena import TABLE_TOP
from teleop.control.controller import Controller

STATE_MARGIN = 0.25  # rad (or m) past a joint's range that the observed state may show
UNLIMITED_TARGET = 2 * math.pi  # rad: joint-target bound of a joint without a range
EE_DELTA_POS = 0.2  # m: bound of an ee_delta translation (target minus actual EE position)
GRIPPER_STATE_FALLBACK = (-1.0, 2.0)  # fingers with no known travel: generous, on the open..closed scale
QUAT = ([-1.0] * 4, [1.0] * 4)
OBJECT_RANGE = 10.0  # m: how far from the robot's base an object's position may be observed


def _joint_range(model: mujoco.MjModel, joint: str) -> tuple[float, float] | None:
    j = model.joint(joint).id
    return (float(model.jnt_range[j, 0]), float(model.jnt_range[j, 1])) if model.jnt_limited[j] else None


def _target_range(model: mujoco.MjModel, actuator: int, joint: str) -> tuple[float, float]:
    """What a joint target can be: the actuator's ctrlrange, else the joint's range."""
    if model.actuator_ctrllimited[actuator]:
        lo, hi = model.actuator_ctrlrange[actuator]
        return float(lo), float(hi)
    return _joint_range(model, joint) or (-UNLIMITED_TARGET, UNLIMITED_TARGET)


def _gripper_state_range(model: mujoco.MjModel, arm: ArmLayout) -> tuple[float, float]:
    """The gripper actuator's length range (finger travel) on the 1 = open .. 0 = closed scale."""
    act = arm.gripper_id
    trn, target, gear = model.actuator_trntype[act], model.actuator_trnid[act, 0], model.actuator_gear[act, 0]
    if trn == mujoco.mjtTrn.mjTRN_JOINT and model.jnt_limited[target]:
        length = model.jnt_range[target] * gear
    elif trn == mujoco.mjtTrn.mjTRN_TENDON and model.tendon_limited[target]:
        length = model.tendon_range[target] * gear
    else:
        return GRIPPER_STATE_FALLBACK
    ends = sorted(arm.gripper_fraction(v) for v in length)
    return ends[0] - 0.1, ends[1] + 0.1


def _box(low: list[float], high: list[float]) -> spaces.Box:
    return spaces.Box(np.asarray(low, np.float32), np.asarray(high, np.float32), dtype=np.float32)


def state_box(model: mujoco.MjModel, arms: list[ArmLayout]) -> spaces.Box:
    low, high = [], []
    for arm in arms:
        for joint in arm.joints:
            lo, hi = _joint_range(model, joint) or (-math.inf, math.inf)
            low.append(lo - STATE_MARGIN)
            high.append(hi + STATE_MARGIN)
        if arm.gripper_id is not None:
            lo, hi = _gripper_state_range(model, arm)
            low.append(lo)
            high.append(hi)
    return _box(low, high)


def ee_pose_box(controller: Controller, action: bool) -> spaces.Box:
    """EE poses around each arm's base: targets within reach above the table (the session's
    clamp), observed poses within twice that (reach is where targets are clamped, not the arm's length)."""
    low, high = [], []
    reach = controller.reach
    for base, arm in zip(controller.base_pos, controller.arms):
        if action:
            low += [base[0] - reach, base[1] - reach, TABLE_TOP, *QUAT[0]]
            high += [base[0] + reach, base[1] + reach, base[2] + reach, *QUAT[1]]
            if arm.gripper_id is not None:
                low.append(0.0)
                high.append(1.0)
        else:
            low += [*(base - 2 * reach), *QUAT[0]]
            high += [*(base + 2 * reach), *QUAT[1]]
    return _box(low, high)


def action_box(mode: str, controller: Controller, arms: list[ArmLayout]) -> spaces.Box:
    """The action vector's bounds; the gripper entry is [0, 1] in every mode."""
    if mode == "ee_pose":
        return ee_pose_box(controller, action=True)
    model = controller.model
    low, high = [], []
    for arm in arms:
        if mode == "joint":
            ranges = [_target_range(model, int(a), j) for a, j in zip(arm.ctrl_ids, arm.joints)]
            low += [r[0] for r in ranges]
            high += [r[1] for r in ranges]
        else:  # ee_delta
            low += [-EE_DELTA_POS] * 3 + [-math.pi] * 3
            high += [EE_DELTA_POS] * 3 + [math.pi] * 3
        if arm.gripper_id is not None:
            low.append(0.0)
            high.append(1.0)
    return _box(low, high)


def make_spaces(
    controller: Controller, arms: list[ArmLayout], mode: str, cameras: list[str], size: tuple[int, int],
    objects: ObjectLayout | None = None,
) -> tuple[dict, spaces.Dict, spaces.Box]:
    """(the export's feature spec, observation space, action space) for these arms and options.

    Shapes and names come from the export's `features` (images declared (H, W, 3),
    as an image export stores them), so the two cannot drift apart.
    """
    spec = features(arms, mode, cameras, size, video=False, channel_first=False, objects=objects)
    obs: dict[str, spaces.Space] = {
        "observation.state": state_box(controller.model, arms),
        "observation.ee_pose": ee_pose_box(controller, action=False),
    }
    if ENV_STATE in spec:
        n = len(objects.names)
        obs[ENV_STATE] = _box(([-OBJECT_RANGE] * 3 + QUAT[0]) * n, ([OBJECT_RANGE] * 3 + QUAT[1]) * n)
    for cam in cameras:
        key = feature_key(cam)
        obs[key] = spaces.Box(0, 255, tuple(spec[key]["shape"]), dtype=np.uint8)
    act = action_box(mode, controller, arms)
    for key, box in [*obs.items(), ("action", act)]:
        if tuple(spec[key]["shape"]) != box.shape:  # a bound for every named entry
            raise AssertionError(f"{key}: bounds {box.shape} do not fit the export's {spec[key]['shape']}")
    return spec, spaces.Dict(obs), act
