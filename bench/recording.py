"""Recording and replay speed.

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
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SUBSTEPS = 25
TIMESTEP = 0.002  # s: 25 x 2 ms is a 20 Hz control tick


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
