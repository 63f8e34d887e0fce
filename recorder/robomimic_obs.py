"""robomimic's observation pairs for a recorded episode: obs[t] before action t, next_obs[t] after it.

robomimic reads data/demo_N/obs/<key>[t] as what was observed before action t
and next_obs/<key>[t] as what was observed after it (its offline-RL configs set
`hdf5_load_next_obs`). A recorded row holds the state *before* its step (qpos,
qvel) but the EE pose the step *reached*, so the pairs are built per key:

  qpos, qvel          obs = the rows. next_obs[t] = obs[t+1]; for the last step, the
                      state after it, got as robomimic's own converter does: play the
                      last action from the last recorded state. That is kept only when
                      the same replay reproduces the recorded transition before it bit
                      for bit (same MuJoCo, same CPU); otherwise the last row is repeated.
  ee_pose             next_obs = the rows (the pose each step reached, measured live);
                      obs[t] = next_obs[t-1], and obs[0] is the pose at the first
                      recorded state (forward kinematics of the recorded model). World
                      frame, x y z (m) then qw qx qy qz, n_arms * 7 values.
  ee_target, gripper  the command in force during step t: obs = the rows, next_obs[t] =
                      obs[t+1], the last repeats it (a command holds until the next one).

`final` says how the last next_obs row of qpos/qvel was obtained: "simulated" or
"repeated". The model is the one the episode recorded, so it compiles; if it did
not, obs/ee_pose[0] would repeat the first reached pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION
_USER = int(mujoco.mjtState.mjSTATE_USER)
_INPUTS = _USER & ~int(mujoco.mjtState.mjSTATE_CTRL)  # applied forces, mocap, eq_active, userdata
_DYNAMIC = int(INTEGRATION) & ~_USER  # what mj_step computes: time, qpos, qvel, act, warmstart

SIMULATED, REPEATED = "simulated", "repeated"


@dataclass
class ObsPairs:
    obs: dict[str, np.ndarray]  # key -> (T, n) float64
    next_obs: dict[str, np.ndarray]
    final: str  # SIMULATED | REPEATED: where the last next_obs of qpos/qvel came from


@dataclass
class Recorded:
    """What the pairs are built from: the recorded model and a few rows of the episode."""

    model_xml: str
    assets: dict[str, bytes]
    timestep: float  # s; 0 keeps the model's own
    substeps: int
    ee_sites: list[str]  # one per arm, row order
    qpos: np.ndarray  # (T, nq)
    qvel: np.ndarray  # (T, nv)
    ee_pose: np.ndarray  # (T, n_arms * 7), reached by each step
    ee_target: np.ndarray  # (T, n_arms * 7)
    gripper: np.ndarray  # (T, n_arms)
    states: np.ndarray  # mjSTATE_INTEGRATION rows 0, T-2, T-1 (fewer when T < 3)
    actions: np.ndarray  # ctrl rows T-2, T-1 (fewer when T < 2)


def _shift(obs: np.ndarray, last: np.ndarray | None = None) -> np.ndarray:
    """next_obs[t] = obs[t+1]; the last row is `last`, or obs[-1] repeated."""
    if not len(obs):
        return obs.copy()
    tail = obs[-1:] if last is None else np.asarray(last, dtype=np.float64).reshape(1, -1)
    return np.concatenate([obs[1:], tail])


def _pose(model: mujoco.MjModel, data: mujoco.MjData, sites: list[int]) -> np.ndarray:
    out = np.empty((len(sites), 7))
    for i, sid in enumerate(sites):
        out[i, :3] = data.site_xpos[sid]
        mujoco.mju_mat2Quat(out[i, 3:], data.site_xmat[sid])
    return out.reshape(-1)


def _simulate(rec: Recorded) -> tuple[np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
    """(EE poses at the first state, (qpos, qvel) after the last step); each None when not known exactly."""
    try:
        model = mujoco.MjModel.from_xml_string(rec.model_xml, rec.assets)
        sites = [model.site(name).id for name in rec.ee_sites]
    except Exception:  # noqa: BLE001 - mujoco raises several kinds; the caller repeats rows instead
        return None, None
    if rec.timestep > 0:
        model.opt.timestep = rec.timestep
    if not len(rec.states) or rec.states.shape[1] != mujoco.mj_stateSize(model, INTEGRATION):
        return None, None
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, rec.states[0], INTEGRATION)
    mujoco.mj_kinematics(model, data)
    first_pose = _pose(model, data, sites)
    if len(rec.states) < 2 or len(rec.actions) < 2:
        return first_pose, None  # a one-step episode: no recorded transition to check the replay on

    def part(spec: int, state: np.ndarray | None = None) -> bytes:
        """Bytes of one part of `state` (or of data's current state)."""
        if state is not None:
            mujoco.mj_setState(model, data, state, INTEGRATION)
        buf = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, buf, spec)
        return buf.tobytes()

    def step(state: np.ndarray, ctrl: np.ndarray) -> None:
        mujoco.mj_setState(model, data, state, INTEGRATION)
        data.ctrl[:] = ctrl
        mujoco.mj_step(model, data, nstep=rec.substeps)

    prev, last = rec.states[-2], rec.states[-1]
    if part(_INPUTS, prev) != part(_INPUTS, last):
        return first_pose, None  # inputs besides ctrl changed between steps: the last step's are unknown
    expected = part(_DYNAMIC, last)
    step(prev, rec.actions[-2])
    if part(_DYNAMIC) != expected:
        return first_pose, None  # this machine does not reproduce the recording
    step(last, rec.actions[-1])
    return first_pose, (data.qpos.copy(), data.qvel.copy())


def obs_pairs(rec: Recorded) -> ObsPairs:
    """obs and next_obs for every robomimic observation key of the episode."""
    T = len(rec.qpos)
    first_pose, after = _simulate(rec) if T else (None, None)
    reached = rec.ee_pose
    if T:
        start = reached[:1] if first_pose is None else first_pose.reshape(1, -1)
        ee_obs = np.concatenate([start, reached[:-1]])
    else:
        ee_obs = reached.copy()
    obs = {"qpos": rec.qpos, "qvel": rec.qvel, "ee_pose": ee_obs, "ee_target": rec.ee_target, "gripper": rec.gripper}
    next_obs = {
        "qpos": _shift(rec.qpos, None if after is None else after[0]),
        "qvel": _shift(rec.qvel, None if after is None else after[1]),
        "ee_pose": reached.copy(),
        "ee_target": _shift(rec.ee_target),
        "gripper": _shift(rec.gripper),
    }
    return ObsPairs(obs, next_obs, SIMULATED if after is not None else REPEATED)
