"""Quality flags: what a reviewer should look at in an episode, from its recording alone.

`scores` measures an episode (one pass over its recorded states, its task's success
test and an exact re-simulation); `flags` compares the scores with `THRESHOLDS`,
the one table of limits (docs/review.md prints it). `long` needs the other episodes
of the same task in the folder: `long_outliers` marks durations past the upper
fence Q3 + 1.5 IQR. Units: metres, seconds, newtons; positions in the world frame.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from replay.engine import resimulate
from replay.episode import Episode
from replay.judge import judge_steps


@dataclass(frozen=True)
class Threshold:
    """A flag is raised when `score` is above `limit` (or, for a bool, equal to `limit`)."""

    flag: str
    score: str
    limit: float | bool
    why: str


THRESHOLDS: tuple[Threshold, ...] = (
    Threshold("long", "duration_s", 1.5, "duration past Q3 + 1.5 IQR of its task's episodes in the folder (needs 4)"),
    Threshold("idle", "idle_fraction", 0.5, "fraction of steps with the end effector still (< 1 cm/s) and the gripper unchanged"),
    Threshold("jerky", "jerk_p90", 400.0, "90th percentile of the end effector's jerk, m/s^3"),
    Threshold("wandering", "path_ratio", 3.0, "end-effector path length over the straight lines between grasps and releases"),
    Threshold("tracking", "tracking_max_mm", 120.0, "largest distance between the end-effector target and the end effector, mm"),
    Threshold("chatter", "rapid_toggles", 2, "gripper close/open toggles less than 0.5 s after the previous one"),
    Threshold("dropped", "drops", 0, "task objects that fell from a grasp, with the task not done within 2 s"),
    Threshold("hard_contact", "max_contact_n", 200.0, "largest contact normal force on the table or a task object, N"),
    Threshold("failed", "success", False, "the task did not succeed"),
    Threshold("not_exact", "bit_exact", False, "re-simulating the recorded ctrl did not give the recorded states bit for bit"),
)
FLAGS = tuple(t.flag for t in THRESHOLDS)
IQR_FENCE = 1.5
IQR_MIN_EPISODES = 4
IDLE_SPEED = 0.01  # m/s
IDLE_GRIPPER = 1e-3  # gripper fraction per step
RAPID_TOGGLE_S = 0.5
DROP_SPEED = 0.5  # m/s downward: falling, not carried
NEAR_EE = 0.06  # m: an object this close to a gripper may be held
LIFTED = 0.02  # m above where it started
DROP_GRACE_S = 2.0
SURFACES = ("table", "floor")  # geom names of the arena (scenes.assembly.arena)
MIN_STRAIGHT = 0.05  # m: the straight-line total never counts as shorter (a path that goes nowhere)


def ee_jerk_p90(pos: np.ndarray, dt: float) -> float:
    """90th percentile over steps of the largest arm's jerk magnitude (pos: (T, n_arms, 3))."""
    if len(pos) < 4 or dt <= 0:
        return 0.0
    jerk = np.diff(pos, n=3, axis=0) / dt**3
    return float(np.percentile(np.linalg.norm(jerk, axis=-1).max(axis=-1), 90))


def gripper_events(gripper: np.ndarray) -> list[int]:
    """Steps where any arm's gripper command crosses half-closed (closes or opens)."""
    closed = gripper < 0.5
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


def _objects(model: mujoco.MjModel) -> list[int]:
    return [int(model.jnt_bodyid[j]) for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]


def scores(episode: Episode, exact: bool = True) -> dict:
    """The episode's quality scores (see THRESHOLDS); `exact`: re-simulate to check bit-exactness."""
    T = episode.steps
    dt = episode.meta.control_dt if episode.meta.control_hz else episode.seconds / max(T, 1)
    pos = episode.ee_pose[:, :, :3] if T else np.zeros((0, 1, 3))
    out: dict = {"duration_s": round(float(episode.seconds), 3), "steps": T}
    if T == 0:
        out.update(idle_fraction=0.0, jerk_p90=0.0, path_ratio=1.0, tracking_max_mm=0.0, gripper_toggles=0,
                   rapid_toggles=0, drops=0, max_contact_n=0.0, success=bool(episode.meta.success), bit_exact=None)
        return out
    speed = np.zeros(T)
    speed[1:] = np.linalg.norm(np.diff(pos, axis=0), axis=-1).max(axis=-1) / dt
    still_gripper = np.ones(T, bool)
    still_gripper[1:] = np.abs(np.diff(episode.gripper, axis=0)).max(axis=-1) < IDLE_GRIPPER
    idle = (speed < IDLE_SPEED) & still_gripper
    idle[0] = False
    events = gripper_events(episode.gripper)
    rapid = sum(1 for a, b in zip(events, events[1:]) if (b - a) * dt < RAPID_TOGGLE_S)
    err = np.linalg.norm(episode.ee_target[:, :, :3] - pos, axis=-1)
    success_steps = judge_steps(episode)
    drops, max_force = _physics_pass(episode, dt, success_steps)
    out.update(
        idle_fraction=round(float(idle[1:].mean()) if T > 1 else 0.0, 4),
        jerk_p90=round(ee_jerk_p90(pos, dt), 2),
        path_ratio=round(path_ratio(pos, events), 3),
        tracking_max_mm=round(float(err.max()) * 1000.0, 2),
        gripper_toggles=len(events),
        rapid_toggles=rapid,
        drops=drops,
        max_contact_n=round(max_force, 2),
        success=bool(episode.meta.success),
        success_step=int(np.argmax(success_steps)) if success_steps.any() else None,
        bit_exact=resimulate(episode, verify=True, warn=False).bit_exact if exact else None,
    )
    return out


def _physics_pass(episode: Episode, dt: float, success_steps: np.ndarray) -> tuple[int, float]:
    """(drops, largest contact normal force on the table or an object) over the recorded states."""
    model = episode.build_model()
    data = mujoco.MjData(model)
    watched = watched_geoms(model)
    objects = _objects(model)
    T = episode.steps
    zs = np.zeros((T, len(objects)))
    near = np.zeros((T, len(objects)), bool)
    force6 = np.zeros(6)
    worst = 0.0
    ee = episode.ee_pose[:, :, :3]
    for k in range(T):
        mujoco.mj_setState(model, data, episode.state[k], mujoco.mjtState.mjSTATE_INTEGRATION)
        mujoco.mj_forward(model, data)
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
    drops = 0
    window = max(1, int(round(1.0 / dt)))
    grace = int(round(DROP_GRACE_S / dt))
    for i in range(len(objects)):
        z = zs[:, i]
        vz = np.zeros(T)
        vz[1:] = np.diff(z) / dt
        held = near[:, i] & (z > z[0] + LIFTED)
        k = 1
        while k < T:
            falling = vz[k] < -DROP_SPEED and not near[k, i]
            if falling and held[max(0, k - window):k].any():
                landed = k
                while landed < T - 1 and vz[landed] < -DROP_SPEED / 5:
                    landed += 1
                if not success_steps[landed:landed + grace].any():  # where it fell is not where the task wants it
                    drops += 1
                k = landed + window  # one fall, one drop
            k += 1
    return drops, worst


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
    """Ids whose duration is past Q3 + 1.5 IQR of their task's; durations: id -> (task, seconds)."""
    by_task: dict[str, list[float]] = {}
    for task, seconds in durations.values():
        by_task.setdefault(task, []).append(seconds)
    fences = {}
    for task, values in by_task.items():
        if len(values) >= IQR_MIN_EPISODES:
            q1, q3 = np.percentile(values, [25, 75])
            fences[task] = q3 + IQR_FENCE * (q3 - q1)
    return {i for i, (task, seconds) in durations.items() if task in fences and seconds > fences[task] + 1e-9}


def quality(s: Mapping, long: bool = False) -> dict:
    """`{"flags": [...], "scores": {...}}` as `teleop inspect --json` and the review page show it."""
    clean = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in s.items()}
    return {"flags": flags(s, long), "scores": clean}
