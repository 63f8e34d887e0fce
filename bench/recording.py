"""Recording and replay speed, plus a small contact-rich scene to record without a robot.

Figures (`measure`):
  record_overhead_pct    extra wall time per control step when recording (both formats),
                         as % of the same loop without recording (no IK in the loop, so
                         the share is larger than in a real session)
  record_append_us       median cost of EpisodeWriter.append on the control thread
  replay_states_per_s    state mode, poses only (mj_setState + mj_kinematics per state)
  replay_forward_states_per_s  state mode with mj_forward per state
  resim_realtime_factor  action replay with bit-for-bit verification: sim s / wall s

The pusher scene (a slider pushing a pile of free boxes) is what the recorder's
tests use: contacts appear, move and vanish, so inexact replay shows at once.
"""

from __future__ import annotations

import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import mujoco
import numpy as np

SUBSTEPS = 25
TIMESTEP = 0.002


def pusher_xml(n_boxes: int = 9) -> str:
    """A position-driven slider ("the arm") and a pile of free boxes on a plane."""
    boxes = []
    for i in range(n_boxes):
        x = 0.25 + 0.09 * (i % 3)
        y = -0.09 + 0.09 * ((i // 3) % 3)
        z = 0.04 + 0.085 * (i // 9) + 0.002 * i
        boxes.append(
            f'<body name="box{i}" pos="{x:.3f} {y:.3f} {z:.3f}"><freejoint/>'
            f'<geom type="box" size=".04 .04 .04" mass="0.2" rgba=".8 .4 .2 1"/></body>'
        )
    return f"""<mujoco model="pusher">
  <compiler angle="radian"/>
  <option timestep="{TIMESTEP}"/>
  <worldbody>
    <light pos="0 0 3"/>
    <geom name="floor" type="plane" size="2 2 0.1" friction="0.9"/>
    <body name="pusher" pos="0 0 0.05">
      <joint name="px" type="slide" axis="1 0 0" range="-0.5 1.2" limited="true" damping="5"/>
      <joint name="py" type="slide" axis="0 1 0" range="-0.6 0.6" limited="true" damping="5"/>
      <geom type="box" size="0.04 0.16 0.04" mass="3"/>
      <site name="ee" pos="0 0 0.05"/>
    </body>
    {''.join(boxes)}
  </worldbody>
  <actuator>
    <position name="ax" joint="px" kp="600" dampratio="1" ctrlrange="-0.5 1.2"/>
    <position name="ay" joint="py" kp="600" dampratio="1" ctrlrange="-0.6 0.6"/>
  </actuator>
</mujoco>"""


def episode_meta(model: mujoco.MjModel, xml: str, index: int, seed: int, substeps: int, *,
                 scene: str = "pusher", robot_spec: dict | None = None, assets: dict | None = None) -> dict:
    """Metadata the way the session fills it, for a model built here."""
    robot_spec = robot_spec or {
        "name": "pusher",
        "arms": [{"ee_site": "ee", "joints": ["px", "py"], "actuators": ["ax", "ay"], "gripper_actuator": None,
                  "gripper_open": None, "gripper_closed": None, "home": [0.0, 0.0]}],
    }
    return {
        "schema_version": 1,
        "scene": scene,
        "robot": robot_spec["name"],
        "robot_spec": robot_spec,
        "model_xml": xml,
        "assets": assets or {},
        "mujoco_version": mujoco.__version__,
        "platform": platform.platform(),
        "machine": platform.machine(),
        "python_version": sys.version.split()[0],
        "seed": seed,
        "control_hz": 1.0 / (model.opt.timestep * substeps),
        "timestep": model.opt.timestep,
        "substeps": substeps,
        "task": "push the boxes",
        "cameras": [],
        "nstate": mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION),
        "nq": model.nq,
        "nv": model.nv,
        "nu": model.nu,
        "start_time": datetime.now(timezone.utc).isoformat(),
        "episode_index": index,
    }


def pusher_ctrl(k: int, seed: int, dt: float) -> np.ndarray:
    """Scripted slider targets: sweep through the pile and back, with a seeded wobble."""
    t = k * dt
    phase = 0.3 * seed
    return np.array([0.45 - 0.55 * np.cos(0.9 * t + phase), 0.25 * np.sin(1.7 * t + phase)])


def record_pusher_episode(
    directory: Path,
    index: int = 0,
    steps: int = 200,
    formats: tuple[str, ...] = ("mcap", "hdf5"),
    seed: int = 0,
    substeps: int = SUBSTEPS,
    on_step: Callable[[int, mujoco.MjData], None] | None = None,
    success: bool = True,
    complete: bool = True,
) -> list[Path]:
    """Run the pusher scene like the session does and record it; returns the files."""
    from recorder import EpisodeWriter, StepRecord

    xml = pusher_xml()
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    site = model.site("ee").id
    nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)
    writer = EpisodeWriter(directory, index, formats, episode_meta(model, xml, index, seed, substeps))
    dt = model.opt.timestep * substeps
    quat = np.empty(4)
    for k in range(steps):
        state = np.empty(nstate)
        mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
        t, qpos, qvel = data.time, data.qpos.copy(), data.qvel.copy()
        data.ctrl[:] = pusher_ctrl(k, seed, dt)
        mujoco.mj_step(model, data, nstep=substeps)
        mujoco.mj_kinematics(model, data)
        mujoco.mju_mat2Quat(quat, data.site_xmat[site])
        target = np.concatenate([data.ctrl, [0.1, 1.0, 0.0, 0.0, 0.0]])
        pose = np.concatenate([data.site_xpos[site], quat])
        commands = [{"source": "bench", "step": k}] if k % 10 == 0 else []
        writer.append(StepRecord(time=t, state=state, ctrl=data.ctrl.copy(), ee_target=target[None],
                                 ee_pose=pose[None], qpos=qpos, qvel=qvel, gripper=np.ones(1),
                                 commands=commands, wall_time=time.time()))
        if on_step is not None:
            on_step(k, data)
    return writer.close(success=success, complete=complete)


# -- measurements -------------------------------------------------------------


def _bench_model(seed: int = 0):
    """The lift scene with a Panda when scenes can build it, else the pusher scene."""
    try:
        import scenes

        scene = scenes.build_scene("lift", scenes.load_robot("panda"), seed=seed, timestep=TIMESTEP)
        arm = scene.arms[0]
        spec = {"name": scene.robot.name, "arms": [{"ee_site": arm.ee_site, "joints": list(arm.joints),
                "actuators": [], "gripper_actuator": None, "gripper_open": None, "gripper_closed": None,
                "home": list(arm.home)}]}
        data = scene.make_data()
        return "lift", scene.model, data, scene.xml, scene.assets, spec, arm.ee_site
    except Exception:  # noqa: BLE001 - fall back to a scene that needs nothing
        xml = pusher_xml()
        model = mujoco.MjModel.from_xml_string(xml)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        return "pusher", model, data, xml, {}, None, "ee"


def _run_loop(model, data, site, steps, writer, nstate, ctrl0, rng_phase) -> tuple[float, list[float]]:
    """The session's per-step work; with a writer also state capture + StepRecord + append."""
    from recorder import StepRecord

    quat = np.empty(4)
    appends = []
    dt = model.opt.timestep * SUBSTEPS
    t0 = time.perf_counter()
    for k in range(steps):
        if writer is not None:
            state = np.empty(nstate)
            mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
            t, qpos, qvel = data.time, data.qpos.copy(), data.qvel.copy()
        data.ctrl[:] = ctrl0 + 0.3 * np.sin(0.8 * k * dt + rng_phase)
        mujoco.mj_step(model, data, nstep=SUBSTEPS)
        mujoco.mj_kinematics(model, data)
        if writer is not None:
            mujoco.mju_mat2Quat(quat, data.site_xmat[site])
            pose = np.concatenate([data.site_xpos[site], quat])[None]
            rec = StepRecord(time=t, state=state, ctrl=data.ctrl.copy(), ee_target=pose, ee_pose=pose,
                             qpos=qpos, qvel=qvel, gripper=np.ones(1), commands=[], wall_time=time.time())
            a0 = time.perf_counter()
            writer.append(rec)
            appends.append(time.perf_counter() - a0)
    return time.perf_counter() - t0, appends


def measure(quick: bool) -> dict[str, float]:
    from recorder import EpisodeWriter
    from replay import load_episode, replay_states, resimulate

    name, model, data, xml, assets, spec, ee_site = _bench_model()
    site = model.site(ee_site).id
    nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)
    ctrl0 = data.ctrl.copy()
    steps = 150 if quick else 400
    reps = 3 if quick else 7
    base, rec, appends = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(reps):
            for recording in (False, True):
                mujoco.mj_resetData(model, data)
                data.ctrl[:] = ctrl0
                writer = None
                if recording:
                    meta = episode_meta(model, xml, r, 0, SUBSTEPS, scene=name, robot_spec=spec, assets=assets)
                    writer = EpisodeWriter(Path(tmp), r, ("mcap", "hdf5"), meta)
                wall, app = _run_loop(model, data, site, steps, writer, nstate, ctrl0, 0.1 * r)
                (rec if recording else base).append(wall / steps)
                appends.extend(app)
                if writer is not None:
                    paths = writer.close(success=True, complete=True)
        episode = load_episode(paths[0])
        ep_model = episode.build_model()
        n_state_passes = 3 if quick else 10
        t0 = time.perf_counter()
        for _ in range(n_state_passes):
            for _ in replay_states(episode, ep_model, kinematics_only=True):
                pass
        kin_rate = n_state_passes * episode.steps / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        for _ in replay_states(episode, ep_model):
            pass
        fwd_rate = episode.steps / (time.perf_counter() - t0)
        result = resimulate(episode, verify=True, model=ep_model, warn=False)
    b, r_ = statistics.median(base), statistics.median(rec)
    return {
        "record_overhead_pct": round(100.0 * (r_ - b) / b, 2),
        "record_step_ms": round(b * 1000, 3),
        "record_append_us": round(statistics.median(appends) * 1e6, 2),
        "replay_states_per_s": round(kin_rate, 0),
        "replay_forward_states_per_s": round(fwd_rate, 0),
        "resim_realtime_factor": round(result.realtime_factor, 1),
        "resim_bit_exact": float(bool(result.bit_exact)),
    }


if __name__ == "__main__":
    import json

    print(json.dumps(measure("--quick" in sys.argv)))
