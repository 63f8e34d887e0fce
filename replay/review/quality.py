"""Quality flags: what a reviewer should look at in an episode, from its recording alone.

`scores` measures an episode (one pass over its recorded states that feeds both its
task's success test and the contact checks, then an exact re-simulation); `flags`
compares the scores with `THRESHOLDS`, the one table of limits: each flag's limit
and every number its score is measured with (a named constant of this module),
each with its unit and why; docs/review.md prints the table and
tests/test_review_limits.py holds the two equal. `long` needs the other episodes of
the same task in the folder: `long_outliers` marks durations past the upper fence
Q3 + IQR_FENCE IQR. Units: metres, seconds, newtons; positions in the world frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from replay.engine import replay_states, resimulate
from replay.episode import Episode
from replay.judge import SuccessJudge
from replay.review.timebase import control_dt, resample

# The numbers that decide the flags (each is a row of THRESHOLDS below; the why is there).
IQR_FENCE = 1.5  # IQR above Q3
IQR_MIN_EPISODES = 4  # episodes of one task
IDLE_SPEED = 0.01  # m/s
IDLE_GRIPPER_SPEED = 0.03  # gripper opening per second (0 closed, 1 open)
JERK_REFERENCE_HZ = 30.0  # Hz
JERK_PERCENTILE = 90  # % of steps
MIN_STRAIGHT = 0.05  # m
GRIPPER_CLOSED = 0.5  # gripper opening
RAPID_TOGGLE_S = 0.5  # s
DROP_SPEED = 0.5  # m/s downward
LANDED_SPEED = 0.1  # m/s downward
NEAR_EE = 0.06  # m
LIFTED = 0.02  # m
DROP_HELD_S = 1.0  # s
DROP_GRACE_S = 2.0  # s
DROP_ONCE_S = 1.0  # s
SURFACES = ("table", "floor")  # geom names of the arena (scenes.assembly.arena) whose contacts count for hard_contact


@dataclass(frozen=True)
class Setting:
    """A number a score is measured with: `name` is the constant of this module that holds `value`, in `unit`."""

    name: str
    value: float
    unit: str
    why: str


@dataclass(frozen=True)
class Threshold:
    """A flag is raised when `score` is above `limit` (or, for a bool, equal to `limit`), in `unit`;
    `settings`: the numbers the score is measured with."""

    flag: str
    score: str
    limit: float | bool
    unit: str
    why: str
    settings: tuple[Setting, ...] = ()


THRESHOLDS: tuple[Threshold, ...] = (
    Threshold("long", "duration_s", IQR_FENCE, "IQR above Q3",
              "longer than the upper fence of its task's durations in the folder: Q3 plus this many IQR", (
                  Setting("IQR_MIN_EPISODES", IQR_MIN_EPISODES, "episodes",
                          "a task with fewer episodes than this in the folder has none judged long"),)),
    Threshold("idle", "idle_fraction", 0.5, "of steps", "fraction of steps with the end effector still and the gripper unchanged", (
        Setting("IDLE_SPEED", IDLE_SPEED, "m/s", "the end effector slower than this is still"),
        Setting("IDLE_GRIPPER_SPEED", IDLE_GRIPPER_SPEED, "opening/s", "the gripper command changing slower than this is unchanged"))),
    Threshold("jerky", "jerk_p90", 400.0, "m/s³",
              f"the end effector's jerk, its JERK_PERCENTILE-th percentile over steps, stated for a {JERK_REFERENCE_HZ:g} Hz reference", (
                  Setting("JERK_REFERENCE_HZ", JERK_REFERENCE_HZ, "Hz",
                          "the path is resampled to this rate before its third difference, so the same motion scores alike "
                          "at any control rate (a finer rate would see more jerk in the same motion)"),
                  Setting("JERK_PERCENTILE", JERK_PERCENTILE, "%", "the score is this percentile over steps: a few spikes do not flag"))),
    Threshold("wandering", "path_ratio", 3.0, "ratio",
              "end-effector path length over the straight lines between start, each grasp or release, and end", (
                  Setting("MIN_STRAIGHT", MIN_STRAIGHT, "m", "the straight lines never count as shorter than this (a path that goes nowhere)"),)),
    Threshold("tracking", "tracking_max_mm", 120.0, "mm", "largest distance between the end-effector target and the end effector"),
    Threshold("chatter", "rapid_toggles", 2, "toggles", "gripper close/open toggles soon after the previous one", (
        Setting("RAPID_TOGGLE_S", RAPID_TOGGLE_S, "s", "a toggle this soon after the previous one is rapid"),
        Setting("GRIPPER_CLOSED", GRIPPER_CLOSED, "opening",
                "a gripper command below this opening is closed: its crossings are the toggles, and the grasps and releases of wandering"))),
    Threshold("dropped", "drops", 0, "drops", "task objects that fell after being held up, with the task not done soon after they landed", (
        Setting("DROP_SPEED", DROP_SPEED, "m/s", "an object going down faster than this, away from every end effector, is falling"),
        Setting("LANDED_SPEED", LANDED_SPEED, "m/s", "a falling object going down slower than this has landed"),
        Setting("NEAR_EE", NEAR_EE, "m", "an object this close to an end effector may be held"),
        Setting("LIFTED", LIFTED, "m", "a held object this far above where it started is held up"),
        Setting("DROP_HELD_S", DROP_HELD_S, "s", "a fall counts when the object was held up within this long before"),
        Setting("DROP_GRACE_S", DROP_GRACE_S, "s", "a fall the task's success follows within this long of landing is a placement, not a drop"),
        Setting("DROP_ONCE_S", DROP_ONCE_S, "s", "after a drop has landed, this long is the same fall (a bounce is not a second drop)"))),
    Threshold("hard_contact", "max_contact_n", 200.0, "N",
              "largest contact normal force on the table, the floor or a task object (fixtures such as a door frame do not count)"),
    Threshold("failed", "success", False, "", "the task did not succeed"),
    Threshold("not_exact", "bit_exact", False, "", "re-simulating the recorded ctrl did not give the recorded states bit for bit"),
)
FLAGS = tuple(t.flag for t in THRESHOLDS)


def limit_rows() -> Iterator[tuple[str, str, float | bool, str, str]]:
    """The table flat, as docs/review.md prints it: (flag, score or constant name, limit or value, unit, why)."""
    for t in THRESHOLDS:
        yield t.flag, t.score, t.limit, t.unit, t.why
        for setting in t.settings:
            yield t.flag, setting.name, setting.value, setting.unit, setting.why


def ee_jerk_p90(pos: np.ndarray, dt: float) -> float:
    """The JERK_PERCENTILE-th percentile over steps of the largest arm's jerk magnitude, m/s³, from the end
    effectors' path (T, n_arms, 3) sampled every `dt` s, resampled to JERK_REFERENCE_HZ before differencing."""
    if dt <= 0:
        return 0.0
    ref_dt = 1.0 / JERK_REFERENCE_HZ
    path = resample(pos, dt, ref_dt)
    if len(path) < 4:  # a third difference needs four samples
        return 0.0
    jerk = np.diff(path, n=3, axis=0) / ref_dt**3
    return float(np.percentile(np.linalg.norm(jerk, axis=-1).max(axis=-1), JERK_PERCENTILE))


def gripper_events(gripper: np.ndarray) -> list[int]:
    """Steps where any arm's gripper command crosses GRIPPER_CLOSED (closes or opens)."""
    closed = gripper < GRIPPER_CLOSED
    changes = np.flatnonzero(np.any(closed[1:] != closed[:-1], axis=-1)) + 1
    return [int(k) for k in changes]


def path_ratio(pos: np.ndarray, events: Sequence[int]) -> float:
    """Path length of the end effectors over the straight lines between start, each grasp or release, and end."""
    if len(pos) < 2:
        return 1.0
    path = float(np.linalg.norm(np.diff(pos, axis=0), axis=-1).sum())
    marks = sorted({0, *events, len(pos) - 1})
    straight = float(sum(np.linalg.norm(pos[b] - pos[a], axis=-1).sum() for a, b in zip(marks, marks[1:])))
    return path / max(straight, MIN_STRAIGHT)


def watched_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Per geom: whether its contact forces count for `hard_contact`: the table and floor
    (scenes' arena names them SURFACES) and every geom of a free-floating task object.
    Fixtures (a door frame, a cupboard) and the robot's own links do not count."""
    free = np.zeros(model.nbody, bool)
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            free[model.jnt_bodyid[j]] = True
    watched = free[model.body_rootid][model.geom_bodyid]
    for g in range(model.ngeom):
        if model.geom(g).name in SURFACES and model.body_weldid[model.geom_bodyid[g]] == 0:
            watched[g] = True
    return watched


def free_bodies(model: mujoco.MjModel) -> list[int]:
    """The bodies with a free joint: the task's loose objects."""
    return [int(model.jnt_bodyid[j]) for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]


@dataclass(frozen=True)
class StatesSeen:
    """What one pass over an episode's recorded states gathers for the scores."""

    success: np.ndarray  # (T,) bool: the task's success test at each state, hold included
    object_z: np.ndarray  # (T, n_objects) m: each free object's height (world z)
    near_ee: np.ndarray  # (T, n_objects) bool: the object within NEAR_EE of an end effector
    max_contact_n: float  # N: largest contact normal force on a watched geom (watched_geoms)


def read_states(episode: Episode) -> StatesSeen:
    """One pass over the recorded states (replay.engine.replay_states) that feeds the task's success test
    and the contact checks alike."""
    model = episode.build_model()
    judge = SuccessJudge(episode, model)
    watched = watched_geoms(model)
    objects = free_bodies(model)
    T = episode.steps
    success = np.zeros(T, bool)
    zs = np.zeros((T, len(objects)))
    near = np.zeros((T, len(objects)), bool)
    force6 = np.zeros(6)
    worst = 0.0
    ee = episode.ee_pose[:, :, :3]
    for k, data in replay_states(episode, model):
        success[k] = judge(data)
        for i, b in enumerate(objects):
            p = data.xpos[b]
            zs[k, i] = p[2]
            near[k, i] = float(np.min(np.linalg.norm(ee[k] - p, axis=-1))) < NEAR_EE
        for c in range(data.ncon):
            g1, g2 = data.contact[c].geom
            if not (watched[g1] or watched[g2]):
                continue
            mujoco.mj_contactForce(model, data, c, force6)
            worst = max(worst, abs(float(force6[0])))
    return StatesSeen(success, zs, near, worst)


def count_drops(seen: StatesSeen, dt: float) -> int:
    """Falls of a task object held up shortly before, after whose landing the task did not succeed soon."""
    T = len(seen.success)
    held_window = max(1, round(DROP_HELD_S / dt))
    once = max(1, round(DROP_ONCE_S / dt))
    grace = round(DROP_GRACE_S / dt)
    drops = 0
    for z, near in zip(seen.object_z.T, seen.near_ee.T):
        vz = np.zeros(T)
        vz[1:] = np.diff(z) / dt
        held = near & (z > z[0] + LIFTED)
        k = 1
        while k < T:
            falling = vz[k] < -DROP_SPEED and not near[k]
            if falling and held[max(0, k - held_window):k].any():
                landed = k
                while landed < T - 1 and vz[landed] < -LANDED_SPEED:
                    landed += 1
                if not seen.success[landed:landed + grace].any():  # where it fell is not where the task wants it
                    drops += 1
                k = landed + once  # one fall, one drop
            k += 1
    return drops


def scores(episode: Episode, exact: bool = True) -> dict:
    """The episode's quality scores (see THRESHOLDS); `exact`: re-simulate to check bit-exactness."""
    T = episode.steps
    dt = control_dt(episode)
    pos = episode.ee_pose[:, :, :3] if T else np.zeros((0, 1, 3))
    out: dict = {"duration_s": round(float(episode.seconds), 3), "steps": T}
    if T == 0:
        out.update(idle_fraction=0.0, jerk_p90=0.0, path_ratio=1.0, tracking_max_mm=0.0, gripper_toggles=0,
                   rapid_toggles=0, drops=0, max_contact_n=0.0, success=bool(episode.meta.success), bit_exact=None)
        return out
    speed = np.zeros(T)
    speed[1:] = np.linalg.norm(np.diff(pos, axis=0), axis=-1).max(axis=-1) / dt
    still_gripper = np.ones(T, bool)
    still_gripper[1:] = np.abs(np.diff(episode.gripper, axis=0)).max(axis=-1) / dt < IDLE_GRIPPER_SPEED
    idle = (speed < IDLE_SPEED) & still_gripper
    idle[0] = False
    events = gripper_events(episode.gripper)
    rapid = sum(1 for a, b in zip(events, events[1:]) if (b - a) * dt < RAPID_TOGGLE_S)
    err = np.linalg.norm(episode.ee_target[:, :, :3] - pos, axis=-1)
    seen = read_states(episode)
    out.update(
        idle_fraction=round(float(idle[1:].mean()) if T > 1 else 0.0, 4),
        jerk_p90=round(ee_jerk_p90(pos, dt), 2),
        path_ratio=round(path_ratio(pos, events), 3),
        tracking_max_mm=round(float(err.max()) * 1000.0, 2),
        gripper_toggles=len(events),
        rapid_toggles=rapid,
        drops=count_drops(seen, dt),
        max_contact_n=round(seen.max_contact_n, 2),
        success=bool(episode.meta.success),
        success_step=int(np.argmax(seen.success)) if seen.success.any() else None,
        bit_exact=resimulate(episode, verify=True, warn=False).bit_exact if exact else None,
    )
    return out


def flags(s: Mapping, long: bool = False) -> list[str]:
    """The flags the scores raise, in THRESHOLDS order; `long` from `long_outliers`."""
    out = []
    for t in THRESHOLDS:
        if t.flag == "long":
            hit = long
        elif isinstance(t.limit, bool):
            hit = s.get(t.score) is t.limit
        else:
            value = s.get(t.score)
            hit = value is not None and value > t.limit
        if hit:
            out.append(t.flag)
    return out


def long_outliers(durations: Mapping[str, tuple[str, float]]) -> set[str]:
    """Ids whose duration is past Q3 + IQR_FENCE IQR of their task's; durations: id -> (task, seconds)."""
    by_task: dict[str, list[float]] = {}
    for task, seconds in durations.values():
        by_task.setdefault(task, []).append(seconds)
    fences = {}
    for task, values in by_task.items():
        if len(values) >= IQR_MIN_EPISODES:
            q1, q3 = np.percentile(values, [25, 75])
            fences[task] = q3 + IQR_FENCE * (q3 - q1)
    return {i for i, (task, seconds) in durations.items() if task in fences and seconds > fences[task] + 1e-9}  # 1e-9 s: float noise


def quality(s: Mapping, long: bool = False) -> dict:
    """`{"flags": [...], "scores": {...}}` as `teleop inspect --json` and the review page show it."""
    clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in s.items()}
    return {"flags": flags(s, long), "scores": clean}
