"""Recording and replay speed, plus a small contact-rich scene to record without a robot.

Figures (`measure`), on the real session (lift, Panda, 25 substeps of 2 ms, IK each tick,
recording MCAP and HDF5):
  record_overhead_pct    how much longer a control tick takes when recording, in a loop that
                         runs in real time at 20 Hz as a person drives: median over pairs of
                         short alternating blocks (one episode open throughout, the session's
                         writer detached in the unrecorded blocks) of the mean tick latency,
                         recorded vs not
  record_control_thread_pct  the recording work timed inside Session.step in that loop (state
                         capture into the recorder's row, the other fields, commit, and any
                         wait for the GIL the writer thread holds) as % of an unrecorded tick
  record_control_us      that work in microseconds per tick
  record_paced_step_ms   the unrecorded tick in that loop (longer than flat out: caches and
                         clocks go cold while the loop sleeps)
  record_flat_out_overhead_pct  the same running flat out (scripted batch recording), where
                         the writer thread competes with the control thread for CPU and GIL
  record_step_ms         the unrecorded control step, flat out
  record_writer_cpu_pct  writer-thread CPU per step (encoding, IO) as % of a flat-out step;
                         it runs beside the control thread (mj_step releases the GIL)
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

from recorder.format import ArmMeta, EpisodeMeta

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
      <site name="ee" pos="0 0 0.05" euler="0 0 0.7"/>
    </body>
    {''.join(boxes)}
  </worldbody>
  <actuator>
    <position name="ax" joint="px" kp="600" dampratio="1" ctrlrange="-0.5 1.2"/>
    <position name="ay" joint="py" kp="600" dampratio="1" ctrlrange="-0.6 0.6"/>
  </actuator>
</mujoco>"""


def episode_meta(model: mujoco.MjModel, xml: str, index: int, seed: int, substeps: int, *,
                 scene: str = "pusher", arms: tuple[ArmMeta, ...] | None = None,
                 assets: dict | None = None) -> EpisodeMeta:
    """Metadata the way the session fills it, for a model built here."""
    arms = arms or (ArmMeta(ee_site="ee", joints=("px", "py"), actuators=("ax", "ay"), home=(0.0, 0.0)),)
    return EpisodeMeta(
        scene=scene,
        robot="pusher",
        arms=arms,
        nstate=mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION),
        nq=model.nq,
        nv=model.nv,
        nu=model.nu,
        control_hz=1.0 / (model.opt.timestep * substeps),
        timestep=model.opt.timestep,
        substeps=substeps,
        seed=seed,
        task="push the boxes",
        model_xml=xml,
        assets=assets or {},
        mujoco_version=mujoco.__version__,
        platform=platform.platform(),
        machine=platform.machine(),
        python_version=sys.version.split()[0],
        start_time=datetime.now(timezone.utc).isoformat(),
        episode_index=index,
        source="script",
    )


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
        target = np.concatenate([data.ctrl, [0.1], quat])  # the slider cannot turn: aim at its own heading
        pose = np.concatenate([data.site_xpos[site], quat])
        commands = [{"source": "bench", "step": k}] if k % 10 == 0 else []
        writer.append(StepRecord(time=t, state=state, ctrl=data.ctrl.copy(), ee_target=target[None],
                                 ee_pose=pose[None], qpos=qpos, qvel=qvel, gripper=np.ones(1),
                                 commands=commands, wall_time=time.time()))
        if on_step is not None:
            on_step(k, data)
    return writer.close(success=success, complete=complete)


# -- measurements -------------------------------------------------------------


def _session(tmp: Path):
    from teleop import Command, Recorder, Session

    session = Session("lift", "panda", seed=0, control_hz=1.0 / (SUBSTEPS * TIMESTEP))
    Recorder(session, tmp, ("mcap", "hdf5"), verify="off")

    def commands(k: int) -> list:
        v = np.array([0.0, 0.004 * np.sin(k / 15.0), 0.003 * np.cos(k / 11.0)])
        return [Command(translation=v, source="bench")]

    for k in range(30):  # warm up IK and caches
        session.step(commands(k))
    return session, commands


def _stop_recording(session) -> tuple[Path, float]:
    """Close the episode without the session's success check (not a recording cost)."""
    recorder = session.recorder
    writer, recorder.writer = recorder.writer, None
    paths = writer.close(success=True, complete=True)
    return paths[0], writer.cpu_seconds


def _paced(session, commands, blocks: int, block_steps: int, period: float) -> tuple[list[float], list[float]]:
    """Mean tick latency (s) of alternating unrecorded / recorded blocks, ticks started every
    `period` s like a session's real-time loop. One episode stays open throughout; in the
    unrecorded blocks the recorder is detached, so the writer thread idles. Blocks are
    short so that the two halves of a pair see the machine alike."""
    recorder = session.recorder
    recorder.start()
    base, rec = [], []
    next_tick = time.perf_counter()
    for b in range(2 * blocks):
        recording = b % 2 == 1
        if recording:
            session.attach(recorder)
        else:
            session.detach(recorder)
        lat = 0.0
        for k in range(block_steps):
            while (now := time.perf_counter()) < next_tick:
                time.sleep(max(0.0, next_tick - now - 0.0003))
            t0 = time.perf_counter()
            session.step(commands(k))
            lat += time.perf_counter() - t0
            next_tick = max(next_tick + period, time.perf_counter())
        (rec if recording else base).append(lat / block_steps)
    session.attach(recorder)
    _stop_recording(session)
    return base, rec


def _flat_out(session, commands, steps: int, record: bool) -> tuple[float, Path | None, float]:
    """Seconds per step running as fast as possible; a recorded run is timed from
    start_episode to the file's close, so the writer thread's whole work counts.
    Also the file and the writer thread's CPU seconds."""
    t0 = time.perf_counter()
    if record:
        session.recorder.start()
    for k in range(steps):
        session.step(commands(k))
    path, cpu = _stop_recording(session) if record else (None, 0.0)
    return (time.perf_counter() - t0) / steps, path, cpu


def measure(quick: bool) -> dict[str, float]:
    from replay import load_episode, replay_states, resimulate

    # Short alternating blocks, compared pairwise: the machine is shared, and load
    # from elsewhere shifts both halves of a pair alike.
    blocks, block_steps = (24, 4) if quick else (96, 4)  # 4 ticks: the halves of a pair are 0.2 s apart
    flat_steps, flat_reps = (300, 1) if quick else (800, 3)  # long: the file's setup and close count too
    period = SUBSTEPS * TIMESTEP  # real time: the writer thread gets the idle part of each tick, as in a session
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        session, commands = _session(tmp)
        flat_base, flat_rec = [], []
        path = None
        session.recorder.record_seconds = 0.0
        paced_base, paced_rec = _paced(session, commands, blocks, block_steps, period)
        control_share = session.recorder.record_seconds / (blocks * block_steps)
        for _ in range(flat_reps):
            flat_base.append(_flat_out(session, commands, flat_steps, False)[0])
            t, path, writer_cpu = _flat_out(session, commands, flat_steps, True)
            flat_rec.append(t)
        episode = load_episode(path)
        model = episode.build_model()
        passes = 3 if quick else 10
        t0 = time.perf_counter()
        for _ in range(passes):
            for _ in replay_states(episode, model, kinematics_only=True):
                pass
        kin_rate = passes * episode.steps / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        for _ in replay_states(episode, model):
            pass
        fwd_rate = episode.steps / (time.perf_counter() - t0)
        result = resimulate(episode, verify=True, model=model, warn=False)
    step = statistics.median(flat_base)
    paced_step = statistics.median(paced_base)
    return {
        "record_overhead_pct": round(100.0 * statistics.median(r / b - 1 for b, r in zip(paced_base, paced_rec)), 2),
        "record_control_thread_pct": round(100.0 * control_share / paced_step, 2),
        "record_flat_out_overhead_pct": round(100.0 * statistics.median(r / b - 1 for b, r in zip(flat_base, flat_rec)), 2),
        "record_step_ms": round(1000.0 * step, 3),
        "record_paced_step_ms": round(1000.0 * paced_step, 3),
        "record_control_us": round(1e6 * control_share, 1),
        "record_writer_cpu_pct": round(100.0 * writer_cpu / (flat_steps * step), 2),
        "replay_states_per_s": round(kin_rate),
        "replay_forward_states_per_s": round(fwd_rate),
        "resim_realtime_factor": round(result.realtime_factor, 1),
        "resim_bit_exact": float(bool(result.bit_exact)),
    }


if __name__ == "__main__":
    import json

    print(json.dumps(measure("--quick" in sys.argv)))
