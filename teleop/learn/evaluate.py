"""`teleop eval`: run a policy in a task scene for many seeds and report how often it succeeds.

The scene is a `TeleopEnv` (teleop.gym), observed and driven exactly as the export
records it, so a policy trained on an export sees what it was trained on. Each
episode is one scene seed (`seed`, `seed + 1`, ...), ended by the task's success or
by `max_seconds`. The success rate comes with a 95% Wilson score interval (honest
at 0 % and 100 % and for few episodes, unlike the normal approximation).

With `record`, every rollout is recorded by the session's `Recorder` as a normal
episode file (`source: "policy"`, `policy`: the policy's path), which replays
bit-exact and opens in `teleop replay --serve` like any other.

Every episode also says how far it got (`reached`: the task's subtasks completed in
order, by `teleop annotate`'s rules) and, when it failed, why (`failure`: never
grasped, dropped, not placed, not at rest, timeout; replay/subtasks/annotate.py), counted
over the run in `failure_breakdown`.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

import numpy as np

from recorder import RecorderError
from replay.subtasks.annotate import FAILURE_REASONS, progress_of
from replay.features import feature_key
from scenes import RobotSpec
from scenes.errors import TeleopError, first_line
from scenes.vary.variation import HELD_OUT_BASE, Variation, eval_look_seed, looks_kinds, physics_kinds
from teleop.learn.gym_env import DEFAULT_MAX_SECONDS, TeleopEnv
from teleop.learn.policy import IMAGE_PREFIX, Policy, PolicyMismatch
from teleop.control.recording import Recorder, arm_metas

Z95 = 1.959963984540054  # standard normal quantile for a two-sided 95 % interval
DEFAULT_SEED = 1000  # past the seeds that recording and generation start from (0, 1, ...)
DEFAULT_CONTROL_HZ = 30.0
DEFAULT_ACTION = "joint"


class EvalError(TeleopError, ValueError):
    """Options that cannot evaluate (no episodes, a negative seed, ...)."""


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (n = 0: the whole [0, 1])."""
    if n <= 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    center = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, center - half), min(1.0, center + half)


@dataclass
class EvalOptions:
    """How to evaluate. cameras: scene camera names or `observation.images.<camera>` keys
    (None: the env's default); image_size (width, height); None for the env's defaults."""

    scene: str = "lift"
    robot: str | Path | RobotSpec = "panda"
    episodes: int = 50
    seed: int = DEFAULT_SEED
    max_seconds: float = DEFAULT_MAX_SECONDS
    control_hz: float = DEFAULT_CONTROL_HZ
    action: str = DEFAULT_ACTION
    cameras: Sequence[str] | None = None
    image_size: tuple[int, int] | None = None
    record: Path | None = None
    formats: tuple[str, ...] = ("mcap",)
    verify: str = "sync"  # the recorder's check of each saved rollout ("off" to skip)
    progress: bool = False  # a progress bar on stderr
    on_episode: Callable[["EpisodeOutcome"], None] | None = None
    # Physics and looks varied per episode (scenes.vary.variation), from held-out seeds unless variation.split is "train".
    variation: Variation | None = None


@dataclass
class EpisodeOutcome:
    seed: int
    success: bool
    steps: int
    seconds: float  # simulated seconds the episode ran
    seconds_to_success: float | None
    wall_seconds: float
    file: str | None = None  # the recorded episode's first file
    replay_bit_exact: bool | None = None  # the recorder's check of it (None: not recorded or not checked)
    reached: list[str] = field(default_factory=list)  # subtasks completed in order, e.g. ["grasp cube"]
    failure: str | None = None  # why it failed (a replay.subtasks.annotate.FAILURE_REASONS key); None: success
    variation: dict | None = None  # its scene's physics and its cameras' look (None: not varied)


@dataclass
class EvalSummary:
    policy: str
    scene: str
    robot: str
    action: str
    control_hz: float
    cameras: list[str]
    image_size: tuple[int, int] | None
    max_seconds: float
    per_episode: list[EpisodeOutcome] = field(default_factory=list)
    wall_seconds: float = 0.0
    steps: int = 0
    step_seconds: float = 0.0  # wall time in env.step and the policy, the rate's denominator
    record: str | None = None
    interrupted: bool = False
    error: str = ""  # the recording's write error that stopped it ('<file>: <cause>'), "" when none
    variation: dict | None = None  # which variation and which seeds (report_variation)

    @property
    def episodes(self) -> int:
        return len(self.per_episode)

    @property
    def successes(self) -> int:
        return sum(e.success for e in self.per_episode)

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes if self.episodes else 0.0

    @property
    def ci95(self) -> tuple[float, float]:
        return wilson_interval(self.successes, self.episodes)

    @property
    def mean_seconds_to_success(self) -> float | None:
        times = [e.seconds_to_success for e in self.per_episode if e.seconds_to_success is not None]
        return sum(times) / len(times) if times else None

    @property
    def failure_breakdown(self) -> dict[str, int]:
        """Failed episodes counted by reason, in FAILURE_REASONS order (reasons with none left out)."""
        counts = {reason: 0 for reason in FAILURE_REASONS}
        for e in self.per_episode:
            if e.failure is not None:
                counts[e.failure] = counts.get(e.failure, 0) + 1
        return {k: v for k, v in counts.items() if v}

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.step_seconds if self.step_seconds > 0 else 0.0

    def to_json(self) -> dict[str, Any]:
        mean = self.mean_seconds_to_success
        return {
            "policy": self.policy,
            "scene": self.scene,
            "robot": self.robot,
            "action": self.action,
            "control_hz": self.control_hz,
            "cameras": self.cameras,
            "image_size": list(self.image_size) if self.image_size else None,
            "max_seconds": self.max_seconds,
            "episodes": self.episodes,
            "successes": self.successes,
            "success_rate": round(self.success_rate, 6),
            "ci95": [round(v, 6) for v in self.ci95],
            "mean_seconds_to_success": None if mean is None else round(mean, 6),
            "failure_breakdown": self.failure_breakdown,
            "per_episode": [asdict(e) for e in self.per_episode],
            "steps": self.steps,
            "steps_per_s": round(self.steps_per_s, 3),
            "wall_seconds": round(self.wall_seconds, 3),
            "record": self.record,
            "interrupted": self.interrupted,
            "error": self.error,
            "variation": self.variation,
        }

    def lines(self) -> list[str]:
        lo, hi = self.ci95
        mean = self.mean_seconds_to_success
        cams = ", ".join(self.cameras) or "no cameras"
        size = f" {self.image_size[0]}x{self.image_size[1]}" if self.image_size and self.cameras else ""
        out = [
            f"policy {self.policy} on {self.scene}/{self.robot} ({self.action} actions, {self.control_hz:g} Hz, {cams}{size})",
            f"success rate {self.successes}/{self.episodes} = {100 * self.success_rate:.1f}% "
            f"(95% Wilson interval {100 * lo:.1f}-{100 * hi:.1f}%)" + (" [interrupted]" if self.interrupted else ""),
            "mean time to success: " + (f"{mean:.2f} s" if mean is not None else "- (no successes)"),
        ]
        for e in self.per_episode:
            got = f", reached: {', '.join(e.reached)}" if e.reached else ""
            what = f"success in {e.seconds_to_success:.2f} s" if e.success else f"failed: {e.failure} ({e.seconds:.2f} s{got})"
            out.append(f"  seed {e.seed}: {what}" + (f"  {e.file}" if e.file else ""))
        if self.record is not None:
            checked = [e.replay_bit_exact for e in self.per_episode if e.file]
            exact = sum(bool(c) for c in checked)
            out.append(f"recorded {len(checked)} rollouts in {self.record} ({exact} checked bit-exact)")
        if self.failure_breakdown:
            out.append("failures: " + ", ".join(f"{k} {v}" for k, v in self.failure_breakdown.items()))
        out.append(f"{self.steps} steps at {self.steps_per_s:.1f} steps/s in {self.wall_seconds:.1f} s")
        if self.variation is not None:
            v = self.variation
            out.append(f"varied: {', '.join(v['kinds'])} ({v['split']} seeds; look seed {v['look_seed']})")
        return out


def report_variation(variation: Variation | None) -> dict | None:
    """What the report says of the variation: the kinds, and which seeds (held out from training, or training ones)."""
    if variation is None or not variation.kinds:
        return None
    return {
        "kinds": list(variation.kinds), "physics": list(physics_kinds(variation.kinds)),
        "looks": list(looks_kinds(variation.kinds, "eval")), "split": variation.split, "looks_seed": variation.looks_seed,
        "look_seed": eval_look_seed(variation.looks_seed, variation.split),
        "training_look_seeds": [0, HELD_OUT_BASE - 1], "held_out_look_seeds": [HELD_OUT_BASE, 2 * HELD_OUT_BASE - 1],
        "physics_stream": variation.split, "overrides": dict(variation.overrides),
        "texture_files": [name for name, _ in variation.texture_files],
    }


def scene_cameras(env: TeleopEnv) -> list[str]:
    return list(env.unwrapped.session.scene.cameras)


def camera_names(wanted: Sequence[str], have: Sequence[str]) -> list[str]:
    """Scene camera names for camera names or `observation.images.<camera>` keys (PolicyMismatch if absent)."""
    by_key = {feature_key(c): c for c in have}
    out = []
    for name in wanted:
        if name.startswith(IMAGE_PREFIX):
            if name not in by_key:
                raise PolicyMismatch(f"policy input {name}: the scene has no such camera (cameras: {', '.join(have) or 'none'})")
            out.append(by_key[name])
        else:
            out.append(name)
    return out


def make_eval_env(opts: EvalOptions) -> TeleopEnv:
    """The environment the options describe (policy image keys resolved to the scene's cameras)."""
    common = dict(control_hz=opts.control_hz, action=opts.action, max_seconds=opts.max_seconds, seed=opts.seed,
                  variation=opts.variation)
    if opts.image_size is not None:
        common["image_size"] = opts.image_size
    cameras = None if opts.cameras is None else list(opts.cameras)
    if cameras and any(c.startswith(IMAGE_PREFIX) for c in cameras):
        probe = TeleopEnv(opts.scene, opts.robot, cameras=(), **common)
        try:
            cameras = camera_names(cameras, scene_cameras(probe))
        finally:
            probe.close()
    return TeleopEnv(opts.scene, opts.robot, cameras=cameras, **common)


def _check(opts: EvalOptions) -> None:
    if isinstance(opts.episodes, bool) or not isinstance(opts.episodes, int) or opts.episodes < 1:
        raise EvalError(f"episodes must be a whole number, 1 or more, got {opts.episodes!r}")
    if isinstance(opts.seed, bool) or not isinstance(opts.seed, int) or opts.seed < 0:
        raise EvalError(f"seed must be a whole number >= 0, got {opts.seed!r}")


def _gripper_open(env: TeleopEnv) -> float:
    """The first arm's commanded gripper, as recorded: 1.0 open, 0.0 closed."""
    arms = env.unwrapped.session.controller.arms
    return 1.0 if arms and arms[0].gripper_open else 0.0


def _progress_of(env: TeleopEnv, states: list[np.ndarray], gripper: list[float], success: bool):
    """How far the rollout got through the task's subtasks, and why it failed (replay/subtasks/annotate.py)."""
    session = env.unwrapped.session
    specs = session.scene.task.subtasks
    arm = arm_metas(session.controller)[0]
    return progress_of(session.controller.model, np.asarray(states), np.asarray(gripper), arm, specs, success)


def run_rollout(env: TeleopEnv, policy: Policy, seed: int, recorder: Recorder | None) -> EpisodeOutcome:
    """One episode of `policy` from the scene of `seed`, recorded when a recorder is given."""
    t0 = time.perf_counter()
    obs, info = env.reset(seed=seed)
    policy.reset()
    if recorder is not None:
        recorder.start()
    steps = 0
    success = bool(info["is_success"])
    states, gripper = [env.get_state()], [_gripper_open(env)]
    while not success:
        obs, _, terminated, truncated, info = env.step(policy.select_action(obs))
        steps += 1
        states.append(env.get_state())
        gripper.append(_gripper_open(env))
        success = bool(info["is_success"])
        if terminated or truncated:
            break
    wall = time.perf_counter() - t0
    seconds = float(info["time"])
    progress = _progress_of(env, states, gripper, success)
    outcome = EpisodeOutcome(seed=seed, success=success, steps=steps, seconds=round(seconds, 6),
                             seconds_to_success=round(seconds, 6) if success else None,
                             wall_seconds=round(wall, 6), reached=list(progress.reached), failure=progress.reason,
                             variation=env.unwrapped.variation_json())
    if recorder is not None:
        files = recorder.save(complete=True)
        if files:
            outcome.file = str(files[0])
            outcome.replay_bit_exact = recorder.verified.get(str(files[0]))
    return outcome


def _progress(enabled: bool, total: int) -> tuple[Progress | None, Any]:
    if not enabled:
        return None, None
    progress = Progress(
        TextColumn("eval"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.description}"), TimeRemainingColumn(),
        console=Console(stderr=True), transient=True,
    )
    return progress, progress.add_task("", total=total)


def evaluate(policy: Policy, opts: EvalOptions) -> EvalSummary:
    """Run `opts.episodes` episodes of `policy` on seeds opts.seed, opts.seed + 1, ...; Ctrl-C ends early
    with the episodes done so far (`interrupted`), the open recording kept, marked incomplete."""
    _check(opts)
    env = make_eval_env(opts)
    try:
        policy.attach(env)
        session = env.session
        summary = EvalSummary(
            policy=policy.name, scene=session.scene_name, robot=session.robot.name, action=env.action_mode,
            control_hz=session.control_hz, cameras=list(env.cameras), image_size=env.image_size if env.cameras else None,
            max_seconds=opts.max_seconds, record=None if opts.record is None else str(opts.record),
            variation=report_variation(opts.variation),
        )
        recorder = None
        if opts.record is not None:
            recorder = Recorder(session, opts.record, opts.formats, verify=opts.verify, source="policy",
                                provenance={"policy": policy.name, "devices": ("policy",)})
        progress, task = _progress(opts.progress, opts.episodes)
        wall0 = time.perf_counter()
        with recorder if recorder is not None else contextlib.nullcontext(), progress or contextlib.nullcontext():
            try:
                for i in range(opts.episodes):
                    outcome = run_rollout(env, policy, opts.seed + i, recorder)
                    summary.per_episode.append(outcome)
                    summary.steps += outcome.steps
                    summary.step_seconds += outcome.wall_seconds
                    if progress is not None:
                        rate = summary.successes / summary.episodes
                        progress.update(task, advance=1, description=f"success {summary.successes}/{summary.episodes} ({100 * rate:.0f}%)")
                    if opts.on_episode is not None:
                        opts.on_episode(outcome)
            except KeyboardInterrupt:
                summary.interrupted = True
                if recorder is not None and recorder.recording:
                    recorder.save(complete=False)
            except RecorderError as exc:  # a full disk: the rollouts recorded before stay whole, the cut one
                summary.error = first_line(exc)  # opens and says it is cut; the report so far goes with the error
                summary.wall_seconds = time.perf_counter() - wall0
                exc.summary = summary  # type: ignore[attr-defined]
                raise
        summary.wall_seconds = time.perf_counter() - wall0
        return summary
    finally:
        env.close()
