"""The observation and action schema: what one frame holds, as LeRobot features, from a simulated state.

Shared by the export (replay/export: recorded states replayed into a dataset) and learning
(teleop/learn: the Gymnasium env and policies read live states the same way), so a policy
trained on an export sees the same vectors, names and cameras when it runs.

Frame k pairs the observation at recorded state k (before control step k) with
the action applied at step k, which is how LeRobot datasets and policies read
(observation -> action). Bimanual robots concatenate arms in recorded order
(left, then right).

Gripper values are normalized to 1 = open .. 0 = closed, in both the state
(the gripper actuator's measured length) and the action (its ctrl target), so
that one policy output fits any gripper's ctrl range; the raw range is stored
per robot in the recording's robot_spec.

Task objects (`observation.environment_state`) are each moving body that is not
the robot's, as position (m) + quaternion wxyz in the robot's base frame (the
first arm's root body), named `<body>.x ... <body>.qz`, in body order.

Poses are position (m, world frame) + quaternion wxyz. q and -q are one
rotation; each arm's quaternions are kept on one hemisphere along an episode
(and commanded ones on the observed one's) so values never flip sign between
frames, which a policy would have to learn around.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import mujoco
import numpy as np

from replay.episode import CONTROL_POLICY, ArmMeta, EpisodeMeta
from replay.errors import TeleopError
from scenes.tasks.geometry import model_task_bodies
from scenes.vary.variation import DISTRACTOR_PREFIX

ACTION_MODES = ("joint", "ee_delta", "ee_pose")
POSE_NAMES = ("x", "y", "z", "qw", "qx", "qy", "qz")
DELTA_NAMES = ("dx", "dy", "dz", "drx", "dry", "drz")
HWC_NAMES = ("height", "width", "channels")
CHW_NAMES = ("channels", "height", "width")


@dataclass
class ArmLayout:
    """Where one arm's joints, actuators, site and gripper live in the model."""

    prefix: str  # "" for a single arm, else e.g. "left/"
    joints: list[str]
    qpos_adr: np.ndarray
    ctrl_ids: np.ndarray
    site_id: int
    gripper_id: int | None
    gripper_open: float
    gripper_closed: float

    def gripper_fraction(self, value: float) -> float:
        """Gripper ctrl or length as 1 = open .. 0 = closed."""
        span = self.gripper_open - self.gripper_closed
        return float((value - self.gripper_closed) / span) if span else 0.0

    @property
    def gripper_name(self) -> list[str]:
        return [f"{self.prefix}gripper"] if self.gripper_id is not None else []


# LeRobot's key for the state of the world outside the robot (ACT and Diffusion read it as an input).
ENV_STATE = "observation.environment_state"


@dataclass
class ObjectLayout:
    """The task's moving bodies (those with a joint, outside the robot) and the robot's base body."""

    names: list[str]
    body_ids: np.ndarray
    base_id: int

    @property
    def feature_names(self) -> list[str]:
        return [f"{n}.{p}" for n in self.names for p in POSE_NAMES]


def object_layout(meta: EpisodeMeta, model: mujoco.MjModel) -> ObjectLayout:
    """The bodies whose pose is the environment state, in model order: every body with a joint of its own
    whose root (the world's child it hangs from) holds none of the arms' joints (so no robot link, finger
    or base), and every task object's body the scene listed (fixed ones too: where the bin stands varies
    by seed); distractors (scenes.vary.variation) left out. Works on any recording's embedded model, old ones
    included (they list no objects)."""
    robot_roots = {int(model.body_rootid[model.jnt_bodyid[model.joint(j).id]]) for arm in meta.arms for j in arm.joints}
    listed = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in model_task_bodies(model) or ()}  # -1: no such body
    ids = [b for b in range(1, model.nbody)
           if (b in listed or (model.body_jntnum[b] > 0 and int(model.body_rootid[b]) not in robot_roots))
           and not model.body(b).name.startswith(DISTRACTOR_PREFIX)]  # their number varies: no task's state
    names = [model.body(b).name or f"body{b}" for b in ids]
    base = min(robot_roots) if robot_roots else 0
    return ObjectLayout(names=names, body_ids=np.asarray(ids, dtype=int), base_id=base)


def _prefix(arm: ArmMeta, index: int, n_arms: int) -> str:
    if n_arms == 1:
        return ""
    head = [j.split("/", 1)[0] for j in arm.joints if "/" in j]
    if len(head) == len(arm.joints) and len(set(head)) == 1:
        return f"{head[0]}/"
    return f"arm{index}/"


def robot_layout(meta: EpisodeMeta, model: mujoco.MjModel) -> list[ArmLayout]:
    """Arm layouts from a recording's arms, resolved against its model."""
    arms = meta.arms
    out = []
    for i, arm in enumerate(arms):
        gripper = arm.gripper_actuator
        out.append(
            ArmLayout(
                prefix=_prefix(arm, i, len(arms)),
                joints=list(arm.joints),
                qpos_adr=np.array([model.joint(j).qposadr[0] for j in arm.joints], dtype=int),
                ctrl_ids=np.array([model.actuator(a).id for a in arm.actuators], dtype=int),
                site_id=model.site(arm.ee_site).id,
                gripper_id=model.actuator(gripper).id if gripper else None,
                gripper_open=float(arm.gripper_open or 0.0),
                gripper_closed=float(arm.gripper_closed or 0.0),
            )
        )
    return out


# LeRobot's name (lerobot-rollout's DAgger strategy) for "a person, not the policy, chose this frame's action".
INTERVENTION = "intervention"
INTERVENTION_FEATURE = {"dtype": "bool", "shape": (1,), "names": None}


def intervention_values(control: np.ndarray | None, source: str, steps: int) -> np.ndarray:
    """(steps, 1) bool: True where a person drove. From the recorded `control` field where the episode
    has it (0 person, 1 policy); otherwise the whole episode is a person's unless its source is a policy."""
    if control is not None:
        return (np.asarray(control)[:steps] != CONTROL_POLICY).reshape(-1, 1)
    return np.full((steps, 1), source != "policy")


# -- cameras ----------------------------------------------------------------

DEFAULT_CAMERAS = ("front", "wrist")


class CameraChoiceError(TeleopError, ValueError):
    """A camera asked for that the scene lacks, or two that would share a dataset key; one line."""


def parse_cameras(text: str | None) -> list[str] | None:
    """'front,wrist' -> ['front', 'wrist']; 'none' or '' -> [] (no images); None -> default."""
    if text is None:
        return None
    names = [c.strip() for c in text.split(",") if c.strip()]
    return [] if names in ([], ["none"]) else names


def resolve_cameras(wanted: list[str] | None, have: list[str]) -> list[str]:
    """Exact names, or a short name that matches one camera per arm (`wrist` -> `left/wrist`, `right/wrist`).

    None: DEFAULT_CAMERAS, those of them the scene has. CameraChoiceError for a name asked for that
    matches none of `have`, or cameras whose dataset keys (feature_key) would be the same.
    """
    explicit = wanted is not None
    out: list[str] = []
    for name in DEFAULT_CAMERAS if wanted is None else wanted:
        matches = [name] if name in have else [c for c in have if c.endswith("/" + name)]
        if not matches:
            if explicit:
                raise CameraChoiceError(f"unknown camera {name!r} (cameras: {', '.join(have) or 'none'})")
            continue
        out += [m for m in matches if m not in out]
    keys = [feature_key(c) for c in out]
    if len(set(keys)) != len(keys):
        raise CameraChoiceError(f"cameras {', '.join(out)} map to the same dataset key; choose fewer")
    return out


def feature_key(camera: str) -> str:
    """Dataset key of a camera: `left/wrist` -> `observation.images.left_wrist`."""
    return "observation.images." + re.sub(r"[^A-Za-z0-9_-]+", "_", camera).strip("_")


def features(
    arms: list[ArmLayout], action: str, cameras: list[str], size: tuple[int, int], video: bool,
    channel_first: bool = False, objects: ObjectLayout | None = None,
) -> dict:
    """The LeRobot feature spec (dtype, shape, names) for these arms, action mode and cameras.

    Cameras are declared (H, W, 3) named height/width/channels, as LeRobot's own
    recorder declares them; `objects` adds the environment state (ENV_STATE) when it
    names any body. `channel_first` asks for (3, H, W) instead, which
    exports made in November 2026 declared (appending to one keeps its layout).
    LeRobot decodes both to the same (3, H, W) tensors. Channel-last is also the
    cheaper one to export: the renderer's rows go to LeRobot's encoder, its PIL
    conversion and its statistics without a transposed copy on the way.
    """
    if action not in ACTION_MODES:
        raise ValueError(f"unknown action mode {action!r} (modes: {', '.join(ACTION_MODES)})")
    state = [n for a in arms for n in [*a.joints, *a.gripper_name]]
    pose = [f"{a.prefix}{n}" for a in arms for n in POSE_NAMES]
    if action == "joint":
        act = state
    elif action == "ee_pose":
        act = [n for a in arms for n in [*(f"{a.prefix}{p}" for p in POSE_NAMES), *a.gripper_name]]
    else:
        act = [n for a in arms for n in [*(f"{a.prefix}{p}" for p in DELTA_NAMES), *a.gripper_name]]
    spec = {
        "observation.state": {"dtype": "float32", "shape": (len(state),), "names": state},
        "observation.ee_pose": {"dtype": "float32", "shape": (len(pose),), "names": pose},
        "action": {"dtype": "float32", "shape": (len(act),), "names": act},
    }
    if objects is not None and objects.names:
        names = objects.feature_names
        spec[ENV_STATE] = {"dtype": "float32", "shape": (len(names),), "names": names}
    width, height = size
    for cam in cameras:
        spec[feature_key(cam)] = {
            "dtype": "video" if video else "image",
            "shape": (3, height, width) if channel_first else (height, width, 3),
            "names": list(CHW_NAMES if channel_first else HWC_NAMES),
        }
    return spec


def is_channel_first(feature: dict) -> bool:
    """Whether an image/video feature is declared (3, H, W) rather than (H, W, 3)."""
    names = list(feature.get("names") or [])
    return bool(names) and names[0] in ("channels", "channel")


def _site_quat(data: mujoco.MjData, site: int) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, data.site_xmat[site])
    return q


def _same_hemisphere(q: np.ndarray, ref: np.ndarray | None) -> np.ndarray:
    """q or -q (the same rotation), whichever is nearer `ref`: no sign flips along an episode."""
    return -q if ref is not None and float(np.dot(q, ref)) < 0 else q


def rotation_vector(q_to: np.ndarray, q_from: np.ndarray) -> np.ndarray:
    """World-frame axis*angle (rad) that turns q_from into q_to, the short way round."""
    conj = np.array([q_from[0], -q_from[1], -q_from[2], -q_from[3]])
    diff = np.empty(4)
    mujoco.mju_mulQuat(diff, q_to, conj)
    if diff[0] < 0:
        diff = -diff
    vel = np.empty(3)
    mujoco.mju_quat2Vel(vel, diff, 1.0)
    return vel


class FrameBuilder:
    """Turns (replayed MjData at step k, recorded row k) into the non-image features.

    Keeps each arm's (and object's) last quaternion so orientations stay on one hemisphere.
    `objects`: also build the environment state (ENV_STATE) of these bodies.
    """

    def __init__(self, arms: list[ArmLayout], action: str, objects: ObjectLayout | None = None):
        self.arms = arms
        self.action = action
        self.objects = objects if objects is not None and objects.names else None
        self._last: list[np.ndarray | None] = [None] * len(arms)
        self._last_obj: list[np.ndarray | None] = [None] * (len(self.objects.names) if self.objects else 0)

    def environment_state(self, data: mujoco.MjData) -> np.ndarray:
        """Each object's position (m) and wxyz quaternion in the robot's base frame, concatenated."""
        objects = self.objects
        assert objects is not None
        base_pos, base_quat = data.xpos[objects.base_id], data.xquat[objects.base_id]
        inv = np.array([base_quat[0], -base_quat[1], -base_quat[2], -base_quat[3]])
        out = np.empty(7 * len(objects.names))
        pos, quat = np.empty(3), np.empty(4)
        for i, body in enumerate(objects.body_ids):
            mujoco.mju_rotVecQuat(pos, data.xpos[body] - base_pos, inv)
            mujoco.mju_mulQuat(quat, inv, data.xquat[body])
            quat = _same_hemisphere(quat, self._last_obj[i])
            self._last_obj[i] = quat.copy()
            out[7 * i : 7 * i + 3] = pos
            out[7 * i + 3 : 7 * i + 7] = quat
        return out

    def __call__(self, data: mujoco.MjData, ctrl: np.ndarray, ee_target: np.ndarray) -> dict[str, np.ndarray]:
        state, pose, act = [], [], []
        for i, arm in enumerate(self.arms):
            q_obs = _same_hemisphere(_site_quat(data, arm.site_id), self._last[i])
            self._last[i] = q_obs
            pos = data.site_xpos[arm.site_id]
            grip_state, grip_act = [], []
            if arm.gripper_id is not None:
                grip_state = [arm.gripper_fraction(data.actuator_length[arm.gripper_id])]
                grip_act = [arm.gripper_fraction(ctrl[arm.gripper_id])]
            state += [*data.qpos[arm.qpos_adr], *grip_state]
            pose += [*pos, *q_obs]
            if self.action == "joint":
                act += [*ctrl[arm.ctrl_ids], *grip_act]
            else:
                t_pos, t_quat = ee_target[i, :3], _same_hemisphere(ee_target[i, 3:], q_obs)
                if self.action == "ee_pose":
                    act += [*t_pos, *t_quat, *grip_act]
                else:
                    act += [*(t_pos - pos), *rotation_vector(t_quat, q_obs), *grip_act]
        frame = {
            "observation.state": np.asarray(state, dtype=np.float32),
            "observation.ee_pose": np.asarray(pose, dtype=np.float32),
            "action": np.asarray(act, dtype=np.float32),
        }
        if self.objects is not None:
            frame[ENV_STATE] = self.environment_state(data).astype(np.float32)
        return frame
