"""Retargeting a leader arm onto another robot: the leader's gripper pose through the so101's kinematics.

An SO-10x leader has the so101's joints, so the so101 model (scenes/robots/so101.xml, MuJoCo
forward kinematics) turns its joint angles into the gripper's pose relative to the leader's
base. What moves the robot is that pose's change since engagement: the position change times
`scale`, and the rotation change, both applied to the robot's end-effector pose at engagement,
expressed relative to the robot's base (x forward, z up on every arm here, as on the leader).
Positions are metres, quaternions wxyz.
"""

from __future__ import annotations

from collections.abc import Mapping

import mujoco
import numpy as np

from scenes.assembly.robot import load_robot

LEADER_ROBOT = "so101"  # the model whose kinematics an SO-10x leader shares


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of two wxyz quaternions."""
    out = np.empty(4)
    mujoco.mju_mulQuat(out, np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    return out


def quat_conj(q: np.ndarray) -> np.ndarray:
    """The inverse of a unit wxyz quaternion."""
    return np.array([q[0], -q[1], -q[2], -q[3]], dtype=float)


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The vector v rotated by the unit wxyz quaternion q."""
    out = np.empty(3)
    mujoco.mju_rotVecQuat(out, np.asarray(v, dtype=float), np.asarray(q, dtype=float))
    return out


def quat_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Radians between two orientations (0..pi)."""
    d = abs(float(np.dot(a, b)) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return 2.0 * float(np.arccos(min(d, 1.0)))


def slerp_toward(a: np.ndarray, b: np.ndarray, max_angle: float) -> np.ndarray:
    """Orientation a turned toward b by at most `max_angle` radians (b itself when closer)."""
    b = b if float(np.dot(a, b)) >= 0 else -b
    angle = quat_angle(a, b)
    if angle <= max_angle:
        return np.asarray(b, dtype=float).copy()
    t = max_angle / angle
    half = angle / 2.0
    out = (np.sin((1 - t) * half) * a + np.sin(t * half) * b) / np.sin(half)
    return out / np.linalg.norm(out)


def to_base(base_pos: np.ndarray, base_quat: np.ndarray, pos: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A world pose expressed in a base frame (both wxyz)."""
    inv = quat_conj(base_quat)
    return rotate(inv, np.asarray(pos) - np.asarray(base_pos)), quat_mul(inv, quat)


def to_world(base_pos: np.ndarray, base_quat: np.ndarray, pos: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pose in a base frame expressed in the world frame (both wxyz)."""
    return np.asarray(base_pos, dtype=float) + rotate(base_quat, pos), quat_mul(base_quat, quat)


class LeaderKinematics:
    """The so101 model alone (base at the origin): joint angles -> gripper site pose relative to the base."""

    def __init__(self) -> None:
        spec = load_robot(LEADER_ROBOT)
        self.reach = spec.reach  # m, what the so101 (and so an SO-10x leader) can reach
        self.model = mujoco.MjModel.from_xml_path(str(spec.mjcf))
        self.data = mujoco.MjData(self.model)
        arm = spec.arms[0]
        self.joints = arm.joints  # shoulder_pan .. wrist_roll: LeRobot's motor names
        self._qadr = [int(self.model.jnt_qposadr[self.model.joint(j).id]) for j in self.joints]
        self._site = self.model.site(arm.ee_site).id
        self._base = self.model.body("base").id

    def pose(self, q: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """(position m, wxyz quaternion) of the gripper site in the leader's base frame, from radians per joint."""
        for name, adr in zip(self.joints, self._qadr):
            self.data.qpos[adr] = q.get(name, 0.0)
        mujoco.mj_kinematics(self.model, self.data)
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, self.data.site_xmat[self._site])
        base_quat = self.data.xquat[self._base].copy()
        return to_base(self.data.xpos[self._base], base_quat, self.data.site_xpos[self._site].copy(), quat)


class Retarget:
    """The leader's gripper motion since engagement, applied to the robot's EE pose at engagement (base frame).

    scale multiplies the position change (the ratio of the robot's reach to the leader's by default);
    the rotation change is applied as it is.
    """

    def __init__(self, scale: float) -> None:
        self.scale = scale
        self.leader0: tuple[np.ndarray, np.ndarray] | None = None
        self.robot0: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def engaged(self) -> bool:
        return self.leader0 is not None

    def engage(self, leader: tuple[np.ndarray, np.ndarray], robot: tuple[np.ndarray, np.ndarray]) -> None:
        """Take the leader's gripper pose and the robot's EE pose (base frame) as the two origins."""
        self.leader0 = (np.asarray(leader[0], dtype=float).copy(), np.asarray(leader[1], dtype=float).copy())
        self.robot0 = (np.asarray(robot[0], dtype=float).copy(), np.asarray(robot[1], dtype=float).copy())

    def target(self, leader: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The robot's EE target (base frame) for the leader's gripper pose now."""
        assert self.leader0 is not None and self.robot0 is not None, "engage first"
        (lp0, lq0), (rp0, rq0) = self.leader0, self.robot0
        pos = rp0 + self.scale * (np.asarray(leader[0]) - lp0)
        turn = quat_mul(leader[1], quat_conj(lq0))  # the leader's rotation since engagement, in its base frame
        quat = quat_mul(turn, rq0)
        return pos, quat / np.linalg.norm(quat)
