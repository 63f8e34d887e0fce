"""Replay an episode: restore recorded states (state mode) or re-simulate ctrl (action mode).

Action replay restores state 0 (mjSTATE_INTEGRATION: physics, user inputs and
warmstart, which is what makes it bit-exact), then per step k sets ctrl[k] and
calls mj_step(nstep=substeps). State k is taken before the session writes tick
k's inputs, so any other input it wrote (mocap, applied forces; normally none)
shows in state k+1 and is applied from there. Verification compares the
simulated dynamic part of the state (everything in INTEGRATION except the user
inputs, which are given, not computed) with the next recorded state, bit for bit.
Exactness is promised only for the MuJoCo version and CPU architecture that recorded.
"""

from __future__ import annotations

import math
import platform
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from replay.episode import Episode, EpisodeMeta, load_episode

INTEGRATION = int(mujoco.mjtState.mjSTATE_INTEGRATION)
USER = int(mujoco.mjtState.mjSTATE_USER)
CTRL = int(mujoco.mjtState.mjSTATE_CTRL)
DYNAMIC = INTEGRATION & ~USER  # computed by mj_step: time, qpos, qvel, act, warmstart, ...
INPUTS = USER & ~CTRL  # applied forces, mocap, eq_active, userdata


@dataclass
class VerifyResult:
    """Outcome of an action replay. first_divergence_step: first recorded step whose state differs."""

    steps: int
    bit_exact: bool | None
    max_abs_diff: float | None
    first_divergence_step: int | None
    compared: int = 0
    sim_seconds: float = 0.0
    wall_seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)

    @property
    def realtime_factor(self) -> float:
        return self.sim_seconds / self.wall_seconds if self.wall_seconds > 0 else math.inf

    def to_dict(self) -> dict:
        out = asdict(self)
        out["realtime_factor"] = None if math.isinf(self.realtime_factor) else self.realtime_factor
        return out


def state_mask(model: mujoco.MjModel, part: int, whole: int = INTEGRATION) -> np.ndarray:
    """Boolean mask of the entries of a `whole` state vector that belong to `part`.

    mj_getState lays components out in the order of their mjtState bits.
    """
    mask: list[bool] = []
    for i in range(whole.bit_length()):
        bit = 1 << i
        if whole & bit:
            mask.extend([bool(part & bit)] * mujoco.mj_stateSize(model, bit))
    return np.array(mask, dtype=bool)


def compat_warnings(meta: EpisodeMeta) -> list[str]:
    """Why bit-exactness is not promised on this machine (empty when it is)."""
    out = []
    rec_ver, rec_arch = meta.mujoco_version, meta.machine
    if rec_ver and rec_ver != mujoco.__version__:
        out.append(f"recorded with MuJoCo {rec_ver}, replaying with {mujoco.__version__}: exactness is not promised")
    if rec_arch and rec_arch != platform.machine():
        out.append(f"recorded on {rec_arch}, replaying on {platform.machine()}: exactness is not promised")
    return out


def _model_data(episode: Episode, model, data):
    model = model if model is not None else episode.build_model()
    data = data if data is not None else mujoco.MjData(model)
    return model, data


def replay_states(
    episode: Episode,
    model: mujoco.MjModel | None = None,
    data: mujoco.MjData | None = None,
    kinematics_only: bool = False,
) -> Iterator[tuple[int, mujoco.MjData]]:
    """Yield (k, data) with data set to recorded state k and forward-computed.

    kinematics_only: mj_kinematics instead of mj_forward (poses only, several times faster).
    """
    model, data = _model_data(episode, model, data)
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    compute = mujoco.mj_kinematics if kinematics_only else mujoco.mj_forward
    set_state = mujoco.mj_setState
    for k, s in enumerate(episode.state):
        set_state(model, data, s, spec)
        compute(model, data)
        yield k, data


def state_poses(episode: Episode, model: mujoco.MjModel | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every body's world pose at every recorded step: xpos (T, nbody, 3), xquat (T, nbody, 4) wxyz."""
    model, data = _model_data(episode, model, None)
    T = episode.steps
    xpos = np.empty((T, model.nbody, 3))
    xquat = np.empty((T, model.nbody, 4))
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    for k, s in enumerate(episode.state):
        mujoco.mj_setState(model, data, s, spec)
        mujoco.mj_kinematics(model, data)
        xpos[k] = data.xpos
        xquat[k] = data.xquat
    return xpos, xquat


def resimulate(
    episode: Episode,
    verify: bool = True,
    model: mujoco.MjModel | None = None,
    data: mujoco.MjData | None = None,
    warn: bool = True,
) -> VerifyResult:
    """Restore state 0, re-step the recorded ctrl, compare every state bit for bit when verify."""
    warnings = compat_warnings(episode.meta)
    if warn:
        for line in warnings:
            print(f"teleop replay: warning: {line}", file=sys.stderr)
    model, data = _model_data(episode, model, data)
    T, substeps = episode.steps, episode.substeps
    states, ctrl = episode.state, episode.ctrl
    result = VerifyResult(steps=T, bit_exact=None, max_abs_diff=None, first_divergence_step=None, warnings=warnings)
    if T == 0:
        result.bit_exact, result.max_abs_diff = (True, 0.0) if verify else (None, None)
        return result
    dyn_mask = state_mask(model, DYNAMIC)
    in_mask = state_mask(model, INPUTS)
    recorded_dyn = np.ascontiguousarray(states[:, dyn_mask])
    recorded_in = np.ascontiguousarray(states[:, in_mask])
    inputs_vary = bool(len(recorded_in)) and not np.array_equal(recorded_in, np.broadcast_to(recorded_in[0], recorded_in.shape))
    buf = np.empty(int(dyn_mask.sum()))
    step, get_state, set_state = mujoco.mj_step, mujoco.mj_getState, mujoco.mj_setState
    dyn_spec, in_spec = DYNAMIC, INPUTS
    worst, first = 0.0, None
    t0 = time.perf_counter()
    set_state(model, data, states[0], mujoco.mjtState.mjSTATE_INTEGRATION)
    data_ctrl = data.ctrl
    for k in range(T):
        if inputs_vary and k + 1 < T:
            set_state(model, data, recorded_in[k + 1], in_spec)
        data_ctrl[:] = ctrl[k]
        step(model, data, nstep=substeps)
        if verify and k + 1 < T:
            get_state(model, data, buf, dyn_spec)
            expected = recorded_dyn[k + 1]
            if buf.tobytes() != expected.tobytes():
                diff = float(np.max(np.abs(buf - expected)))
                if math.isnan(diff):
                    diff = math.inf
                worst = max(worst, diff)
                if first is None:
                    first = k + 1
    result.wall_seconds = time.perf_counter() - t0
    result.sim_seconds = T * substeps * model.opt.timestep
    if verify:
        result.compared = T - 1
        result.bit_exact = first is None
        result.max_abs_diff = worst
        result.first_divergence_step = first
    return result


def verify_file(path: str | Path, warn: bool = True) -> VerifyResult:
    """Load a saved episode and re-simulate it with verification (what the recorder runs after save)."""
    return resimulate(load_episode(path), verify=True, warn=warn)
