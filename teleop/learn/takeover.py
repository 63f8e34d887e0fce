"""A policy drives a served session; the operator takes over by touching any device (DAgger-style).

    takeover = Takeover(session, policy, env)      # env: a TeleopEnv around the same session
    commands, ctrl = takeover.steer(session, commands)   # each tick, before Session.step

The policy drives until a device moves the arm: a gizmo drag, a held key, a
SpaceMouse push or a gripper button hands control to the operator at once, in
the same tick, so the operator's input is never overridden by the policy. The
keyboard's `p` or the panel's button (a "policy" event) hands it back; the
policy then starts afresh (its action queue is cleared) from where the operator
left the arm. A reset (a new scene) gives control back to the policy too.

Each tick tells the attached recorder who drove (`Recorder.control`), so every
recorded step stores it and the export can write LeRobot's `intervention`
feature. Observations and actions are the export's, through the TeleopEnv: the
policy sees what it was trained on.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from devices.command import Command
from replay.episode import CONTROL_HUMAN, CONTROL_POLICY
from scenes.errors import first_line
from pathlib import Path

from teleop.learn.gym_env import TeleopEnv
from replay.features import feature_key
from teleop.learn.policy import LeRobotPolicy, Policy, PolicyMismatch, ScriptedPolicy
from teleop.control.session import Session

Driver = Literal["policy", "operator"]
HAND_BACK_EVENT = "policy"  # devices.command.EVENTS: the keyboard's `p`, the panel's button
TIMING_WINDOW = 100  # ticks the inference figures are taken over


def moves_arm(command: Command) -> bool:
    """True when a device's command moves an arm or its gripper (episode events alone do not)."""
    return (
        command.target_pos is not None
        or command.target_quat is not None
        or command.gripper is not None
        or bool(np.any(command.translation))
        or bool(np.any(command.rotation))
    )


@dataclass(frozen=True)
class Handover:
    """One change of driver: at which tick of the scene (session.controller.steps), to whom, and why."""

    step: int
    driver: Driver
    reason: str


class Takeover:
    """Decides each tick whether the policy or the operator drives `session`."""

    def __init__(self, session: Session, policy: Policy, env: TeleopEnv) -> None:
        if env.session is not session:
            raise ValueError("the environment must observe the served session")
        self.session = session
        self.policy = policy
        self.env = env
        self.driver: Driver = "policy"
        self.problem: str | None = None  # why the policy stopped (an error in it): it cannot drive again
        self.handovers: list[Handover] = []
        self.policy_steps = 0
        self.operator_steps = 0
        self._inference_s: collections.deque[float] = collections.deque(maxlen=TIMING_WINDOW)
        self._observe_s: collections.deque[float] = collections.deque(maxlen=TIMING_WINDOW)
        self._model = session.controller.model
        self._tick = session.controller  # a new one also when an episode starts from its seed's initial state (same model)
        self._requests: collections.deque[Driver] = collections.deque()  # from the panel's threads
        policy.attach(env)
        policy.reset()
        self._tell_recorder()

    @classmethod
    def for_session(cls, session: Session, policy: Policy) -> "Takeover":
        """A takeover of `session` by `policy`, observed as the policy was trained (`env_for`)."""
        return cls(session, policy, env_for(session, policy))

    def close(self) -> None:
        """Free the observation renderer (its GL context)."""
        self.env.close()

    # -- requests from other threads (the panel) -------------------------------
    def request(self, driver: Driver) -> None:
        """Ask for `driver` from the next tick on (thread-safe: the loop applies it)."""
        self._requests.append(driver)

    # -- the tick -------------------------------------------------------------
    def steer(self, session: Session, commands: Sequence[Command]) -> tuple[list[Command], np.ndarray | None]:
        """This tick's (commands, ctrl) for Session.step: the devices' own, or theirs plus the policy's action."""
        commands = list(commands)
        if session.controller.model is not self._model or session.controller is not self._tick:  # reset between ticks (a button): a new scene
            self._model, self._tick = session.controller.model, session.controller
            self._switch("policy", "new scene")
        while self._requests:
            wanted = self._requests.popleft()
            self._switch(wanted, "panel")
        if any(HAND_BACK_EVENT in c.events for c in commands):
            self._switch("policy", "handed back")
        touched = next((c for c in commands if moves_arm(c)), None)
        if touched is not None and self.driver == "policy":
            self._switch("operator", f"{touched.source or 'a device'} moved")
        self._tell_recorder()
        if self.driver == "operator" or any("reset" in c.events for c in commands):
            self.operator_steps += self.driver == "operator"
            return commands, None
        try:
            t0 = time.perf_counter()
            observation = self.env.observe()
            t1 = time.perf_counter()
            action = self.policy.select_action(observation)
            t2 = time.perf_counter()
            extra, ctrl = self.env.to_step(np.asarray(action, dtype=np.float64))
        except Exception as exc:  # noqa: BLE001 - a failing policy hands control to the operator, never stops the loop
            self.problem = first_line(exc)
            session.stats.note(f"policy stopped: {self.problem}")
            self._switch("operator", "policy failed")
            self._tell_recorder()
            return commands, None
        self._observe_s.append(t1 - t0)
        self._inference_s.append(t2 - t1)
        self.policy_steps += 1
        return [*commands, *extra], ctrl

    def _switch(self, driver: Driver, reason: str) -> None:
        if driver == "policy" and self.problem is not None:
            self.session.stats.note(f"the policy cannot drive again: {self.problem}")
            return
        if driver == "policy":
            self.policy.reset()  # a fresh start from where the arm is: no stale action chunk
        if driver == self.driver:
            return
        self.driver = driver
        self.handovers.append(Handover(self.session.controller.steps, driver, reason))
        self.session.stats.note(f"{'policy' if driver == 'policy' else 'operator'} driving ({reason})")

    def _tell_recorder(self) -> None:
        recorder = self.session.recorder
        if recorder is not None:
            recorder.control = CONTROL_POLICY if self.driver == "policy" else CONTROL_HUMAN

    # -- figures --------------------------------------------------------------
    @property
    def takeovers(self) -> int:
        """Times the operator took control."""
        return sum(h.driver == "operator" for h in self.handovers)

    def inference_ms(self) -> tuple[float | None, float | None]:
        """(median, max) of the policy's select_action over the last TIMING_WINDOW ticks it drove, ms."""
        values = list(self._inference_s)
        return (float(np.median(values)) * 1e3, max(values) * 1e3) if values else (None, None)

    def observe_ms(self) -> float | None:
        """Median time to build the policy's observation (state restore + cameras), ms."""
        values = list(self._observe_s)
        return float(np.median(values)) * 1e3 if values else None

    def status(self) -> dict:
        median, worst = self.inference_ms()
        observe = self.observe_ms()
        return {
            "name": self.policy.name,
            "driver": self.driver,
            "takeovers": self.takeovers,
            "policy_steps": self.policy_steps,
            "operator_steps": self.operator_steps,
            "inference_ms": None if median is None else round(median, 3),
            "inference_max_ms": None if worst is None else round(worst, 3),
            "observe_ms": None if observe is None else round(observe, 3),
            "problem": self.problem,
            "handovers": [{"step": h.step, "driver": h.driver, "reason": h.reason} for h in self.handovers[-20:]],
        }


SCRIPT_PREFIX = "script:"


def load_policy(spec: str | Path, device: str = "cpu") -> Policy:
    """`script:FILE` (a scenes/scripts JSON played as EE targets) or a LeRobot pretrained-model folder."""
    text = str(spec)
    if text.startswith(SCRIPT_PREFIX):
        return ScriptedPolicy(text[len(SCRIPT_PREFIX):])
    return LeRobotPolicy.load(text, device=device)


def env_for(session: Session, policy: Policy) -> TeleopEnv:
    """A TeleopEnv around the live `session` with the policy's cameras, image size and action mode.

    A LeRobot checkpoint says what it was trained on (its image inputs, and the action
    mode and rate of its training data where that dataset is here); a scripted policy
    gives EE poses and looks at no camera. PolicyMismatch if the rate or a camera does
    not fit the session.
    """
    options: dict = {"action": "ee_pose", "cameras": ()}
    if isinstance(policy, LeRobotPolicy):
        trained = policy.trained_on
        have = {feature_key(c): c for c in session.scene.cameras}
        missing = [k for k in trained.cameras if k not in have]
        if missing:
            raise PolicyMismatch(f"policy input {missing[0]}: scene {session.scene_name} has no such camera "
                                 f"(cameras: {', '.join(session.scene.cameras) or 'none'})")
        options = {"action": trained.action or "joint", "cameras": [have[k] for k in trained.cameras]}
        if trained.image_size is not None:
            options["image_size"] = trained.image_size
        if trained.fps is not None and abs(trained.fps - session.control_hz) > 1e-6:
            raise PolicyMismatch(f"the policy was trained on {trained.fps:g} frames/s; the session runs at "
                                 f"{session.control_hz:g} Hz (use --control-hz {trained.fps:g})")
    env = TeleopEnv(session=session, **options)
    try:
        if isinstance(policy, LeRobotPolicy):
            policy.checkpoint.check(env)
    except BaseException:
        env.close()
        raise
    return env
