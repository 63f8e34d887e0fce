"""Leader arms and a real follower, on the servo emulators (issue 47): `teleop bench --only leader`.

LeRobot's own SOLeader and SOFollower, unpatched, talk to byte-level Feetech emulators on pseudo-terminals
(tests/servo_emulator.py, each in a process of its own), and the simulated so101 runs at 30 Hz in wall-clock
time in this process, driven by the leader device (devices/lerobot_leader.py) as `teleop run` drives it.

- `leader_read_ms`: one `get_action()` of LeRobot's SOLeader (a sync read of 6 servos), median;
- `leader_to_tick_ms`: p95 from a step change of the leader's elbow at the emulator (its own clock, which is
  CLOCK_MONOTONIC like ours) to the end of the first tick whose joint target has it; goal <= 45 ms;
- `leader_tracking_rad`: p95 joint error (qpos) of the simulated so101 following a 0.5 Hz, 0.3 rad sine on every
  joint, after the ease-in, the leader at time t compared with the arm one `leader_to_tick` (median) later;
  goal <= 0.05;
- `follower_hz`: Goal_Position writes a second at the follower's emulator while it mirrors that motion;
  goal >= the control rate (30).
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np

from devices.leader_connect import connect_leader, parse_leader_spec
from devices.lerobot_leader import make_leader
from teleop.control.follower import open_follower
from teleop.control.session import Session
from tests.servo_emulator import MOTOR_NAMES, FeetechEmulator, from_lerobot

CONTROL_HZ = 30.0
ARM = MOTOR_NAMES[:5]  # the so101's arm joints, LeRobot's motor names
SINE_HZ, SINE_RAD = 0.5, 0.3


def _sine_motion(emulator: FeetechEmulator, seconds: float, step: float = 0.01) -> tuple[dict, callable]:
    """A looping 0.5 Hz, 0.3 rad sine on every arm joint (raw positions for the emulator), and the same in radians."""
    ts = [round(i * step, 6) for i in range(int(round(seconds / step)) + 1)]

    def joint(t: float) -> float:
        return SINE_RAD * math.sin(2 * math.pi * SINE_HZ * t)

    positions = {}
    for motor, cal in emulator.calibration.items():
        if motor == "gripper":
            positions[str(cal.id)] = [from_lerobot(50.0, cal, "range_0_100") for _ in ts]
        else:
            positions[str(cal.id)] = [from_lerobot(math.degrees(joint(t)), cal, "degrees") for t in ts]
    return {"t": ts, "positions": positions, "loop": True}, joint


def _read_ms(emulator: FeetechEmulator, cal_dir: Path, reads: int) -> float:
    spec = parse_leader_spec("so101_leader", f"{emulator.port}:id=bench:calibration={cal_dir}")
    leader = connect_leader(spec)
    try:
        times = []
        for _ in range(reads):
            t0 = time.perf_counter()
            leader.get_action()
            times.append(time.perf_counter() - t0)
    finally:
        leader.disconnect()
    return float(np.median(times) * 1000.0)


class _Loop:
    """The so101 session ticked at 30 Hz in wall-clock time by the leader device, its ticks kept."""

    def __init__(self, leader) -> None:
        self.session = Session(scene="lift", robot="so101", seed=0, control_hz=CONTROL_HZ)
        self.leader = leader
        self.rows: list[tuple[float, np.ndarray, np.ndarray]] = []  # (monotonic at tick end, ctrl, qpos) of the arm
        ctrl = self.session.controller
        model = ctrl.model
        self.qadr = [model.jnt_qposadr[model.joint(j).id] for j in self.session.scene.arms[0].joints]
        self.cadr = list(ctrl.arms[0].ctrl_ids)
        self.next = time.monotonic()

    def run(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        dt = 1.0 / CONTROL_HZ
        while time.monotonic() < end:
            controller = self.session.controller
            self.session.step(self.leader.poll(controller, dt))
            data = controller.data
            self.rows.append((time.monotonic(), data.ctrl[self.cadr].copy(), data.qpos[self.qadr].copy()))
            self.next += dt
            pause = self.next - time.monotonic()
            if pause > 0:
                time.sleep(pause)
            else:
                self.next = time.monotonic()  # late: no burst of catch-up ticks

    def engaged(self, timeout_s: float = 20.0) -> None:
        deadline = time.monotonic() + timeout_s
        while self.leader.status() == "easing in" or not self.rows:
            if time.monotonic() > deadline:
                raise RuntimeError("the leader did not engage")
            self.run(0.2)


def measure(quick: bool = False) -> dict[str, float]:
    steps = 10 if quick else 30
    track_s = 6.0 if quick else 14.0
    with tempfile.TemporaryDirectory(prefix="bench-leader-") as tmp:
        tmp_path = Path(tmp)
        cal = tmp_path / "cal"
        with FeetechEmulator.start(tmp_path, role="leader") as arm, \
                FeetechEmulator.start(tmp_path, role="follower", rate=3000.0) as real:
            arm.write_calibration_file(cal, "bench")
            real.write_calibration_file(tmp_path / "fcal", "bench")
            read_ms = _read_ms(arm, cal, 60 if quick else 300)

            leader = make_leader("so101_leader", f"{arm.port}:id=bench:calibration={cal}", log=lambda line: None)
            leader.start()
            loop = _Loop(leader)
            leader.check(loop.session.controller)
            try:
                # -- latency: step changes of the elbow (0.2 rad) at the emulator, each found in the ticks ----------
                loop.engaged()
                elbow = ARM.index("elbow_flex")
                latencies = []
                for k in range(steps):
                    target = 0.2 if k % 2 == 0 else 0.0
                    changed_at = arm.set_action({"elbow_flex.pos": math.degrees(target)})
                    first = len(loop.rows)
                    loop.run(0.4)
                    hit = next((t for t, c, _ in loop.rows[first:] if abs(c[elbow] - target) < 0.05), None)
                    if hit is not None:
                        latencies.append((hit - changed_at) * 1000.0)
                to_tick_ms = float(np.percentile(latencies, 95)) if latencies else float("nan")
                lag_s = float(np.median(latencies)) / 1000.0 if latencies else 0.0

                # -- tracking, with the follower mirroring the arm ------------------------------------------------
                motion, joint = _sine_motion(arm, 2.0)
                follower = open_follower(f"so101_follower:{real.port}:id=bench:calibration={tmp_path / 'fcal'}",
                                         loop.session)
                try:
                    started = arm.play(motion)
                    first = len(loop.rows)
                    loop.run(track_s)
                    goals_before_end = real.goal_log()
                finally:
                    follower.close()
            finally:
                leader.close()
        rows = loop.rows[first:]
        settle = started + 3.0  # the ease-in from the last step pose, and the arm's first swing
        errors = [np.max(np.abs(q - joint(t - lag_s - started)))
                  for t, _, q in rows if t > settle]
        tracking = float(np.percentile(errors, 95)) if errors else float("nan")
        times = [g["t"] for g in goals_before_end if g["id"] == 1 and started + 1.0 <= g["t"] <= rows[-1][0]]
        follower_hz = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0  # writes a second, one servo
    return {
        "leader_read_ms": round(read_ms, 3),
        "leader_to_tick_ms": round(to_tick_ms, 1),
        "leader_tracking_rad": round(tracking, 4),
        "follower_hz": round(follower_hz, 1),
    }


if __name__ == "__main__":
    print(measure(quick=True))
