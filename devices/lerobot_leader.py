"""LeRobot leader arms (SO-100, SO-101, Koch) as input devices, through LeRobot's own teleoperator classes.

`so101_leader:PORT[:id=NAME][:calibration=DIR][:map=FILE][:scale=F][:arm=K]` (and `so100_leader`,
`koch_leader`). LeRobot and its servo SDKs are imported only when a leader starts (the `hardware`
extra). Calibration is LeRobot's: the file `lerobot-calibrate` wrote, found where LeRobot looks
(or in `calibration=DIR`); the leader is connected with `connect(calibrate=False)` and checked here,
because LeRobot's own `calibrate()` waits on stdin.

Two ways to drive, chosen against the session's robot before the first tick:
  joints   the map's robot (the so101 for the repository's maps): the leader's joints, through the
           joint map (devices/joint_map.py), are the arm's joint targets, applied without IK.
  retarget any other robot, SO-10x leaders only: the leader's gripper pose through the so101's
           kinematics (devices/retarget.py); its change since engagement, the position times
           `scale` (default: the robots' reach ratio), moves the robot's EE target.
The leader's gripper gives the robot's gripper opening (0 closed .. 1 open) either way.

Engaging without a jump (GELLO's rule): at the start of an episode, and when the leader comes
back after an unplug, an arm whose targets are more than 0.5 rad (a joint target) or 5 cm / 0.5 rad
(the EE target) from where the leader says eases toward it, at most 0.05 rad or 1 cm (and 0.05 rad
of turn) a control tick. Both the choice and the ease start from the arm's targets, never its joints'
positions: pressed on the table or a cube, or left by a policy, an arm's targets lie past where it stands.
status() says "easing in" until it has caught up. A reader thread of its own polls the bus
(`get_action()`), so a slow or unplugged bus never stalls the control tick; unplugged (its reads
failing for half a second), the device says "disconnected", sends nothing (the arm holds its last
target) and tries to reopen the port every second. Retargeting keeps the episode's origin across an
unplug, so a leader moved while unplugged brings the arm to where it says, eased in, rather than
shifting the origin.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from devices.command import Command
from devices.joint_map import JointMap, JointMapError, builtin_map_path, load_joint_map
from devices.leader_connect import (
    LEADER_TYPES, MOTORS, UNITS, LeaderError, LeaderSpec, connect_leader, drop_leader, parse_leader_spec,
)
from devices.retarget import LEADER_ROBOT, LeaderKinematics, Retarget, quat_angle, slerp_toward, to_base, to_world
from devices.view import SessionView
from scenes.errors import first_line

ENGAGE_JOINT_RAD = 0.5  # a joint further than this from the leader: ease in
EASE_JOINT_RAD = 0.05  # per control tick
ENGAGE_POS_M = 0.05  # retargeting: an EE target further than this (or ENGAGE_TURN_RAD) from the leader's: ease in
ENGAGE_TURN_RAD = 0.5
EASE_POS_M = 0.01  # per control tick
EASE_TURN_RAD = 0.05  # per control tick
READ_PERIOD_S = 0.005  # the reader thread's pause between bus reads (a sync read takes about 0.5-3 ms)
RECONNECT_S = 1.0  # between tries to reopen an unplugged leader
LOST_AFTER_S = 0.5  # reads failing for this long (each of them since) mean the leader is gone, not a glitch

def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@runtime_checkable
class _Notes(Protocol):
    """A view that keeps operator notes (the session's controller: the page and `teleop run` show them)."""

    def note(self, message: str) -> None: ...


def _reading(action: dict) -> dict[str, float]:
    """LeRobot's {"shoulder_pan.pos": value} as {"shoulder_pan": value}."""
    return {k.removesuffix(".pos"): float(v) for k, v in action.items()}


class LeaderArm:
    """One LeRobot leader arm driving one arm of the session (see the module docstring)."""

    def __init__(self, spec: LeaderSpec, log: Callable[[str], None] | None = None) -> None:
        if spec.kind not in LEADER_TYPES:
            raise LeaderError(f"unknown leader type {spec.kind!r} (known: {', '.join(LEADER_TYPES)})")
        self.spec = spec
        self.kind = spec.kind
        self.arm = spec.arm
        self.name = f"{spec.kind}:{spec.port}" + (f":arm={spec.arm}" if spec.arm else "")
        self.log = log or _stderr
        self.problem = ""  # why the leader is disconnected, for the panel
        self.readings = 0  # bus reads since start
        self.reconnects = 0
        try:
            self.map = load_joint_map(spec.map or builtin_map_path(spec.kind))
        except JointMapError as exc:
            raise LeaderError(str(exc)) from None
        self._check_map(self.map)
        self._leader = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected = False
        self._sample: dict[str, float] | None = None
        self._engage = True  # (re)engage at the next poll: an episode began or the leader came back
        self._new_episode = True  # the next engagement starts a new retargeting origin
        self._easing = False
        self._last_time = -math.inf
        self._announced = ""
        self._notes: list[str] = []
        # chosen by choose_mode(): "joints" or "retarget"
        self.mode: str | None = None
        self._index: list[int | None] = []  # arm joint -> index of the map rule that drives it
        self._out_q: np.ndarray | None = None
        self._out_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._kin: LeaderKinematics | None = None
        self._retarget: Retarget | None = None

    def _check_map(self, jmap: JointMap) -> None:
        where = f"{self.spec.kind}: map {jmap.path}"
        if jmap.units != UNITS[self.spec.kind]:
            raise LeaderError(f"{where}: units = {jmap.units!r}, but LeRobot reads a {self.spec.kind} in {UNITS[self.spec.kind]!r}")
        unknown = [j for j in jmap.leader_joints if j not in MOTORS]
        if unknown:
            raise LeaderError(f"{where}: no leader joint {unknown[0]!r} on a {self.spec.kind} (it has {', '.join(MOTORS)})")

    # -- life cycle -------------------------------------------------------
    def start(self) -> None:
        """Connect and check now (a wrong setup is one line before anything runs), then read in the background."""
        self._leader = connect_leader(self.spec)
        try:
            self._sample = _reading(self._leader.get_action())
        except Exception as exc:  # noqa: BLE001 - the first read: any failure means the leader is unusable
            drop_leader(self._leader)
            self._leader = None
            raise LeaderError(f"{self.name}: the servos do not answer reads ({first_line(exc)})") from None
        self.readings = 1
        self._connected = True  # said at the first tick, as "connected" or "easing in"
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-reader", daemon=True)
        self._thread.start()

    def restart(self) -> None:
        """A new episode: engage again (with the ease-in if the arm is far from the leader)."""
        with self._lock:
            self._engage = self._new_episode = True
            self._easing = False

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)
        leader, self._leader = self._leader, None
        if leader is not None:
            try:
                leader.disconnect()
            except Exception:  # noqa: BLE001 - closing a leader that went away
                drop_leader(leader)
        self._connected = False

    @property
    def finished(self) -> bool:
        return False

    def status(self) -> str:
        if self._stop.is_set():
            return "closed"
        if not self._connected:
            return "disconnected"
        return "easing in" if self._easing else "connected"

    # -- reading thread ---------------------------------------------------
    def _run(self) -> None:
        failing_since: float | None = None  # when the reads in a row that failed began
        while not self._stop.is_set():
            leader = self._leader
            if leader is None:
                if self._stop.wait(RECONNECT_S):
                    break
                self._reopen()
                continue
            try:
                sample = _reading(leader.get_action())
            except Exception as exc:  # noqa: BLE001 - unplugged: pyserial, LeRobot and the OS raise many kinds
                # one lost answer (a busy host or USB adapter) is a glitch: the arm holds its target a tick or two
                now = time.monotonic()
                failing_since = now if failing_since is None else failing_since
                if now - failing_since >= LOST_AFTER_S:
                    failing_since = None
                    self._lost(first_line(exc))
                else:
                    self._stop.wait(READ_PERIOD_S)
                continue
            failing_since = None
            with self._lock:
                self._sample = sample
                self.readings += 1
            self._stop.wait(READ_PERIOD_S)

    def _reopen(self) -> None:
        try:
            leader = connect_leader(self.spec, patient=False)  # the next try is RECONNECT_S away
            sample = _reading(leader.get_action())
        except Exception as exc:  # noqa: BLE001 - still unplugged (or not answering yet): try again later
            self.problem = first_line(exc)
            return
        if self._stop.is_set():  # closed meanwhile: this port is no one's
            drop_leader(leader)
            return
        with self._lock:
            self._leader = leader
            self._sample = sample
            self._connected = True
            self._engage = True
            self.problem = ""
            self.reconnects += 1
        self._announce("connected")

    def _lost(self, why: str) -> None:
        leader, self._leader = self._leader, None
        if leader is not None:
            drop_leader(leader)
        with self._lock:
            self._connected = False
            self._easing = False
            self.problem = why
        self._announce("disconnected")

    def _announce(self, status: str) -> None:
        """Say a status change once, on the terminal now and as a session note at the next poll."""
        why = " (the servos stopped answering: unplugged? trying again every second; the arm holds)" if status == "disconnected" else ""
        line = f"{self.name}: {status}{why}"
        with self._lock:
            if status == self._announced:
                return
            self._announced = status
            self._notes.append(line)
        self.log(line)

    # -- control tick -----------------------------------------------------
    def check(self, view: SessionView) -> None:
        """SceneChecked, before the first tick: a leader that cannot drive this robot is one line (choose_mode)."""
        self.choose_mode(view)

    def choose_mode(self, view: SessionView) -> str:
        """Choose joints or retargeting for the session's robot, set it up and return it; LeaderError when neither fits."""
        if not 0 <= self.arm < view.n_arms:
            raise LeaderError(f"{self.name}: arm={self.arm} but the robot has {view.n_arms} arm(s)")
        robot = view.robot_name
        if robot == self.map.robot:
            names = view.joint_names(self.arm)
            by_robot = {r.robot: i for i, r in enumerate(self.map.joints)}
            missing = [r.robot for r in self.map.joints if r.robot not in names]
            if missing:
                raise LeaderError(f"{self.name}: map {self.map.path} names joint {missing[0]!r}, which {robot} lacks "
                                  f"(its joints: {', '.join(names)})")
            self._index = [by_robot.get(n) for n in names]
            self.mode = "joints"
            return self.mode
        if self.spec.kind == "koch_leader" or self.map.robot != LEADER_ROBOT:
            raise LeaderError(
                f"{self.name} drives the {self.map.robot} joint for joint only (no {self.spec.kind.removesuffix('_leader')} "
                f"model here to retarget from): use --robot {self.map.robot}, or an SO-100/SO-101 leader for {robot}"
            )
        self._kin = self._kin or LeaderKinematics()  # the so101 model, compiled once
        scale = self.spec.scale if self.spec.scale is not None else view.reach / self._kin.reach
        self._retarget = Retarget(scale)
        self.mode = "retarget"
        return self.mode

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        """The newest leader reading as this tick's commands (nothing while disconnected: the arm holds)."""
        if self.mode is None:
            self.choose_mode(view)
        with self._lock:
            sample = self._sample
            connected = self._connected
            engage, self._engage = self._engage, False
            new_episode, self._new_episode = self._new_episode, False
        now = view.time
        if now < self._last_time:  # the session was reset (a new episode that nobody announced)
            engage = new_episode = True
        self._last_time = now
        if not connected or sample is None:
            if engage:  # keep the request for when the leader is back
                with self._lock:
                    self._engage = True
                    self._new_episode = self._new_episode or new_episode
            self._flush_notes(view)
            return []
        gripper = self.map.gripper_opening(sample)
        if self.mode == "joints":
            commands = self._joints(view, sample, engage, gripper)
        else:
            commands = self._pose(view, sample, engage, new_episode, gripper)
        self._announce("easing in" if self._easing else "connected")
        self._flush_notes(view)
        return commands

    def _flush_notes(self, view: SessionView) -> None:
        """Hand the status lines said since the last tick to the session's notes (on the control thread)."""
        with self._lock:
            notes, self._notes = self._notes, []
        if isinstance(view, _Notes):
            for line in notes:
                view.note(line)

    def _joints(self, view: SessionView, sample: dict[str, float], engage: bool, gripper: float | None) -> list[Command]:
        """Position mode: the map's joint angles, eased in at most EASE_JOINT_RAD a tick after engaging."""
        if engage or self._out_q is None:
            self._out_q = view.joint_targets(self.arm).astype(float)
        lo, hi = view.joint_limits(self.arm)
        values = self.map.robot_joints(sample)
        rules = self.map.joints
        want = np.array([self._out_q[i] if k is None else values[rules[k].robot] for i, k in enumerate(self._index)])
        want = np.minimum(np.maximum(want, lo), hi)
        if engage:  # judged against the targets it eases from, not the joints' positions: an arm pressed on the
            # table or a cube (or left by a policy) has targets past where it stands, and a jump from them is a jump
            self._easing = bool(np.max(np.abs(want - self._out_q), initial=0.0) > ENGAGE_JOINT_RAD)
        if self._easing:
            step = np.clip(want - self._out_q, -EASE_JOINT_RAD, EASE_JOINT_RAD)
            self._out_q = self._out_q + step
            if np.max(np.abs(want - self._out_q), initial=0.0) <= 1e-9:
                self._out_q, self._easing = want, False
        else:
            self._out_q = want
        return [Command(joints=self._out_q.copy(), gripper_opening=gripper, arm=self.arm, source=self.name)]

    def _pose(self, view: SessionView, sample: dict[str, float], engage: bool, new_episode: bool,
              gripper: float | None) -> list[Command]:
        """Retargeting: the leader's gripper motion since engagement moves the EE target, eased at most 1 cm a tick."""
        assert self._kin is not None and self._retarget is not None
        leader = self._kin.pose(self.map.robot_joints(sample))
        base_pos, base_quat = view.base_pose(self.arm)
        if new_episode or not self._retarget.engaged:
            self._retarget.engage(leader, to_base(base_pos, base_quat, *view.target_pose(self.arm)))
        pos, quat = to_world(base_pos, base_quat, *self._retarget.target(leader))
        if engage or self._out_pose is None:
            here = view.target_pose(self.arm)
            self._out_pose = (here[0].astype(float), here[1].astype(float))
            far = np.linalg.norm(pos - self._out_pose[0]) > ENGAGE_POS_M or quat_angle(quat, self._out_pose[1]) > ENGAGE_TURN_RAD
            self._easing = bool(far)
        if self._easing:
            cur_pos, cur_quat = self._out_pose
            gap = pos - cur_pos
            dist = float(np.linalg.norm(gap))
            turned = quat_angle(cur_quat, quat) <= EASE_TURN_RAD  # slerp_toward reaches it this tick
            new_pos = pos.copy() if dist <= EASE_POS_M else cur_pos + gap * (EASE_POS_M / dist)
            self._out_pose = (new_pos, slerp_toward(cur_quat, quat, EASE_TURN_RAD))
            if dist <= EASE_POS_M and turned:
                self._easing = False
        else:
            self._out_pose = (pos, quat)
        commands = [Command(target_pos=self._out_pose[0].copy(), target_quat=self._out_pose[1].copy(), arm=self.arm, source=self.name)]
        if gripper is not None:
            commands.append(Command(gripper_opening=gripper, arm=self.arm, source=self.name))
        return commands

    def reading(self) -> dict[str, float] | None:
        """The newest leader reading (LeRobot's units: degrees or -100..100, gripper 0..100), for panels."""
        with self._lock:
            return None if self._sample is None else dict(self._sample)


def make_leader(kind: str, arg: str, n_arms: int = 1, log: Callable[[str], None] | None = None) -> LeaderArm:
    """A leader device from its spec word's parts (not started); LeaderError for a bad option or map."""
    return LeaderArm(parse_leader_spec(kind, arg, n_arms), log=log)
