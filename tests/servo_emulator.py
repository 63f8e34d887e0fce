"""Servo emulators on pseudo-terminals: LeRobot's real motor buses talk to them as to a USB servo adapter.

Each emulator runs in a process of its own (`python -m tests.servo_emulator CONFIG`), because LeRobot's SDKs
time a status packet out after ~34 ms, which a busy test process could miss. The child opens a pty, sets it
raw and answers packets byte for byte (tests/servo_wire.py); the test drives it over a pipe (JSON lines on the
child's stdin, one JSON answer per line on its stdout). The child exits when that pipe closes, so a test that
dies leaves no emulator behind.

    with FeetechEmulator.start(tmp_path, role="leader") as arm:     # six STS3215 at ids 1..6 (an SO-101)
        arm.write_calibration_file(tmp_path / "cal", "arm")         # the file LeRobot's connect() checks
        leader = SOLeader(SOLeaderTeleopConfig(port=arm.port, id="arm", calibration_dir=tmp_path / "cal"))
        leader.connect(calibrate=False)
        t = arm.set_action({"elbow_flex.pos": 20.0})               # degrees, LeRobot's own scale; t: monotonic

Positions are raw Present_Position steps (0..4095 a turn, after the servo's homing offset). A leader's come
from a motion (`motion=`, `play()`) or `set_positions()`; a follower's move to each Goal_Position written while
torque is on. Every register write is logged (`writes()`, `goal_log()`, `torque_log()`) with its
time.monotonic(), which is CLOCK_MONOTONIC: the test process can compare its own times with it.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import termios
import time
import tty
import weakref
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import ClassVar

if __package__ in (None, ""):  # run as a file: python tests/servo_emulator.py CONFIG
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests.servo_wire import (  # noqa: E402
    STS3215_DEFAULTS,
    XL330_DEFAULTS,
    DynamixelBus,
    FeetechBus,
    Log,
    Motion,
    Servo,
)

ROOT = Path(__file__).resolve().parent.parent
RESOLUTION = 4096  # encoder steps a turn (STS3215, XL330)

# The motor names of LeRobot's SO-100/SO-101 and Koch arms (ids 1..6), which are the sim so101's joint names.
MOTOR_NAMES = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")

STS3215 = 777  # Feetech model numbers
XL330_M077 = 1190  # Dynamixel model numbers: Koch leader
XL330_M288 = 1200  # Koch follower, ids 3..6
XL430_W250 = 1060  # Koch follower, ids 1..2


# -- calibration and LeRobot's scales -----------------------------------------------------------------------


@dataclass(frozen=True)
class ServoCalibration:
    """One motor's calibration, the fields of LeRobot's MotorCalibration (raw steps)."""

    id: int
    drive_mode: int
    homing_offset: int
    range_min: int
    range_max: int

    @property
    def mid(self) -> float:
        """Centre of the calibrated range: LeRobot's 0 degrees."""
        return (self.range_min + self.range_max) / 2


@dataclass(frozen=True)
class ArmScale:
    """How a LeRobot device scales each motor: `body` for ids 1..5 ("degrees" or "m100_100"), the gripper 0..100.

    `apply_drive_mode`: FeetechMotorsBus flips RANGE_* values of an inverted motor, DynamixelMotorsBus does not;
    LeRobot's degrees never flip.
    """

    body: str
    apply_drive_mode: bool

    def mode(self, name: str) -> str:
        return "range_0_100" if name == "gripper" else self.body


SO_DEGREES = ArmScale("degrees", True)  # SOLeader / SOFollower with use_degrees=True
SO_M100 = ArmScale("m100_100", True)  # use_degrees=False
KOCH_LEADER = ArmScale("m100_100", False)  # KochLeader: RANGE_M100_100 joints, 0..100 gripper

SO101_CALIBRATION = {  # a plausible SO-101 after LeRobot's calibrate(): drive modes 0, wrist_roll a full turn
    "shoulder_pan": ServoCalibration(1, 0, -1012, 760, 3340),
    "shoulder_lift": ServoCalibration(2, 0, 437, 820, 3250),
    "elbow_flex": ServoCalibration(3, 0, -871, 870, 3090),
    "wrist_flex": ServoCalibration(4, 0, 1302, 830, 3170),
    "wrist_roll": ServoCalibration(5, 0, -155, 0, 4095),
    "gripper": ServoCalibration(6, 0, 1450, 2020, 3410),
}
KOCH_CALIBRATION = {  # a plausible Koch leader: elbow inverted, shoulder_pan and wrist_roll full turns
    "shoulder_pan": ServoCalibration(1, 0, 1024, 0, 4095),
    "shoulder_lift": ServoCalibration(2, 0, -1025, 780, 3300),
    "elbow_flex": ServoCalibration(3, 1, 2047, 900, 3100),
    "wrist_flex": ServoCalibration(4, 0, -2050, 860, 3210),
    "wrist_roll": ServoCalibration(5, 0, 0, 0, 4095),
    "gripper": ServoCalibration(6, 0, 512, 1900, 2900),
}


def to_lerobot(raw: float, cal: ServoCalibration, mode: str, apply_drive_mode: bool = True) -> float:
    """Raw Present_Position -> the value LeRobot reports: degrees = (raw - mid) * 360 / 4095 (unclamped);
    range_0_100 / m100_100 clamp raw to the calibrated range first."""
    if mode == "degrees":
        return (raw - cal.mid) * 360 / (RESOLUTION - 1)
    inverted = apply_drive_mode and cal.drive_mode
    share = (min(cal.range_max, max(cal.range_min, raw)) - cal.range_min) / (cal.range_max - cal.range_min)
    if mode == "range_0_100":
        return 100 - 100 * share if inverted else 100 * share
    if mode == "m100_100":
        value = 200 * share - 100
        return -value if inverted else value
    raise ValueError(f"unknown scale {mode!r}")


def from_lerobot(value: float, cal: ServoCalibration, mode: str, apply_drive_mode: bool = True) -> int:
    """LeRobot's value (degrees, 0..100, -100..100) -> the nearest raw position that reads back as it."""
    if mode == "degrees":
        return int(round(value * (RESOLUTION - 1) / 360 + cal.mid))
    inverted = apply_drive_mode and cal.drive_mode
    if mode == "range_0_100":
        share = (100 - value if inverted else value) / 100
    elif mode == "m100_100":
        share = ((-value if inverted else value) + 100) / 200
    else:
        raise ValueError(f"unknown scale {mode!r}")
    return int(round(cal.range_min + min(1.0, max(0.0, share)) * (cal.range_max - cal.range_min)))


def step_of(cal: ServoCalibration, mode: str) -> float:
    """One raw step in LeRobot's units for this motor: the tolerance of a value read back."""
    if mode == "degrees":
        return 360 / (RESOLUTION - 1)
    return (100 if mode == "range_0_100" else 200) / (cal.range_max - cal.range_min)


def mismatched(calibration: dict[str, ServoCalibration], motor: str = "elbow_flex") -> dict[str, ServoCalibration]:
    """A copy whose `motor` range differs from the servo's registers: LeRobot's is_calibrated is then False."""
    cal = calibration[motor]
    return {**calibration, motor: replace(cal, range_max=cal.range_max - 37)}


def write_calibration_file(path: Path, calibration: dict[str, ServoCalibration]) -> Path:
    """Write `calibration` as LeRobot writes it (draccus JSON of MotorCalibration per motor name) to `path`."""
    import draccus
    from lerobot.motors import MotorCalibration

    path.parent.mkdir(parents=True, exist_ok=True)
    motors = {name: MotorCalibration(**asdict(cal)) for name, cal in calibration.items()}
    with open(path, "w") as f, draccus.config_type("json"):
        draccus.dump(motors, f, indent=4)
    return path


def load_motion(motion: dict | str | Path) -> dict:
    """A leader's motion as the emulator takes it: {"t": [s...], "positions": {id: [raw...]}, "loop": bool}.

    Given as that dict, a JSON file of it, or an .npz with arrays `t` (T,) in seconds and `positions` (T, N)
    raw steps, optional `ids` (N,) (default 1..N) and `loop` (default true). Between samples positions are
    interpolated linearly; after the last one the motion loops, or with loop false holds its end."""
    if isinstance(motion, dict):
        return motion
    path = Path(motion)
    if path.suffix == ".npz":
        import numpy as np

        with np.load(path) as data:
            table = np.asarray(data["positions"])
            ids = [int(i) for i in data["ids"]] if "ids" in data else list(range(1, table.shape[1] + 1))
            loop = bool(data["loop"]) if "loop" in data else True
            return {"t": [float(t) for t in data["t"]], "loop": loop,
                    "positions": {i: [int(round(v)) for v in table[:, k]] for k, i in enumerate(ids)}}
    return json.loads(path.read_text())


# -- LeRobot's timeouts on a loaded test machine ----------------------------------------------------------------


def connect_device(device, tries: int = 3) -> None:
    """`device.connect(calibrate=False)` (a LeRobot teleoperator or robot), tried again on ConnectionError.

    LeRobot's SDKs give a status packet 34-50 ms and KochLeader's connect does ~40 writes without retries: on
    a loaded 2-core machine the test process itself is sometimes not scheduled in that time (the emulator has
    answered). The handshake's unretried pings make a late answer "Missing motor IDs" (a RuntimeError): that is
    tried again too; a wrong model number is not."""
    for attempt in range(tries):
        try:
            device.connect(calibrate=False)
            return
        except (ConnectionError, RuntimeError) as exc:
            if device.bus.port_handler.is_open:
                device.bus.port_handler.closePort()
            late = isinstance(exc, ConnectionError) or "Missing motor IDs" in str(exc)
            if attempt == tries - 1 or not late:
                raise


def read_retrying(read, tries: int = 3):
    """`read()` (e.g. `leader.get_action`), tried again on ConnectionError: for devices that do not retry a
    sync read themselves (KochLeader), where a loaded machine can miss the SDK's timeout."""
    for attempt in range(tries):
        try:
            return read()
        except ConnectionError:
            if attempt == tries - 1:
                raise
    raise AssertionError("unreachable")


# -- the parent side -----------------------------------------------------------------------------------------


class EmulatorError(RuntimeError):
    """The emulator process did not start, answer or accept a command."""


class ServoEmulator:
    """A handle on one emulator process: a bus of servos behind the pty at `port`. Use `start()`."""

    protocol: ClassVar[str]
    default_model: ClassVar[int]
    default_scale: ClassVar[ArmScale]
    default_calibration: ClassVar[dict[str, ServoCalibration]]

    def __init__(self, proc: subprocess.Popen, port: str, ids: list[int], calibration: dict[str, ServoCalibration],
                 scale: ArmScale, log_path: Path, stderr_path: Path) -> None:
        self.proc = proc
        self.port = port
        self.ids = ids
        self.calibration = calibration
        self.scale = scale
        self.log_path = log_path
        self.stderr_path = stderr_path
        self._buffer = b""
        self._finalizer = weakref.finalize(self, _stop_process, proc)

    @classmethod
    def start(
        cls,
        tmp_path: Path,
        *,
        ids=range(1, 7),
        role: str = "leader",
        motion: dict | str | Path | None = None,
        positions: dict[int, int] | None = None,
        model: int | dict[int, int] | None = None,
        calibration: dict[str, ServoCalibration] | None = None,
        scale: ArmScale | None = None,
        rate: float | None = None,
        baudrate: int = 1_000_000,
        registers: dict[int, dict[str, int]] | None = None,
        name: str | None = None,
    ) -> ServoEmulator:
        """Start an emulator process and wait for its pty.

        ids: the servos on the bus (empty: a port with no servo, which answers nothing).
        role: "leader" (positions come from `motion` / `set_positions` only) or "follower" (Present_Position
          moves to each Goal_Position written while torque is on, at `rate` raw steps/s; None: at once).
        motion: {"t": [s...], "positions": {id: [raw...]}, "loop": bool}, or a JSON / .npz file (`load_motion`);
          it starts when the emulator does (`play()` starts another at a known time).
        positions: raw start positions by id (default: the centre of each motor's calibrated range).
        model: model number of every servo, or by id (default: the real one; another number: a wrong model).
        calibration: written into the registers (Homing_Offset, limits, Drive_Mode) by motor name
          (default: a plausible calibrated arm); `write_calibration_file()` writes the matching file.
        baudrate: the servos' rate; they hear only a host whose port is set to it (as on a real bus).
        registers: more initial register values, {id: {register name: value}}.
        """
        tmp_path = Path(tmp_path)
        tmp_path.mkdir(parents=True, exist_ok=True)
        ids = [int(i) for i in ids]
        calibration = dict(calibration if calibration is not None else cls.default_calibration)
        scale = scale or cls.default_scale
        tag = name or f"{cls.protocol}-{os.getpid()}-{time.monotonic_ns()}"
        log_path = tmp_path / f"{tag}.writes.jsonl"
        stderr_path = tmp_path / f"{tag}.stderr.txt"
        motion = load_motion(motion) if motion is not None else None
        models = model if isinstance(model, dict) else {i: model or cls.default_model for i in ids}
        by_id = {cal.id: (motor, cal) for motor, cal in calibration.items()}
        start = {}
        for i in ids:
            regs = cls.calibration_registers(by_id[i][1]) if i in by_id else {}
            regs.update((registers or {}).get(i, {}))
            raw = (positions or {}).get(i, round(by_id[i][1].mid) if i in by_id else 2048)
            start[i] = {"model": int(models.get(i, cls.default_model)), "registers": regs, "position": int(raw)}
        config = {
            "protocol": cls.protocol, "servos": start, "role": role, "rate": rate, "motion": motion,
            "baud_register": cls.baud_register(baudrate), "log": str(log_path),
            "names": {cal.id: motor for motor, cal in calibration.items()},
        }
        env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        with open(stderr_path, "wb") as err:
            proc = subprocess.Popen([sys.executable, "-m", "tests.servo_emulator", json.dumps(config)], cwd=ROOT, env=env,
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err)
        handle = cls(proc, "", ids, calibration, scale, log_path, stderr_path)
        hello = handle._answer(timeout=30)
        handle.port = hello["port"]
        return handle

    @classmethod
    def calibration_registers(cls, cal: ServoCalibration) -> dict[str, int]:
        return {"Homing_Offset": cal.homing_offset, "Min_Position_Limit": cal.range_min, "Max_Position_Limit": cal.range_max}

    @classmethod
    def baud_register(cls, baudrate: int) -> int:
        table = FeetechBus.bauds if cls.protocol == "feetech" else DynamixelBus.bauds
        for value, rate in table.items():
            if rate == baudrate:
                return value
        raise ValueError(f"{cls.protocol} servos cannot run at {baudrate} baud (they can at {sorted(table.values())})")

    # -- the control pipe

    def _answer(self, timeout: float = 10.0) -> dict:
        deadline = time.monotonic() + timeout
        while b"\n" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or self.proc.poll() is not None:
                raise EmulatorError(f"{self.protocol} emulator did not answer (exit {self.proc.poll()}): {self.stderr()[-2000:]}")
            if select.select([self.proc.stdout], [], [], min(left, 0.5))[0]:
                chunk = os.read(self.proc.stdout.fileno(), 65536)
                if not chunk:
                    continue
                self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\n", 1)
        answer = json.loads(line)
        if not answer.get("ok"):
            raise EmulatorError(answer.get("error", "command failed"))
        return answer

    def command(self, op: str, **fields) -> dict:
        """Send one command to the child; its answer (raises EmulatorError on failure)."""
        if self.proc.poll() is not None:
            raise EmulatorError(f"{self.protocol} emulator has exited ({self.proc.returncode}): {self.stderr()[-2000:]}")
        self.proc.stdin.write((json.dumps({"op": op, **fields}) + "\n").encode())
        self.proc.stdin.flush()
        return self._answer()

    def stderr(self) -> str:
        try:
            return self.stderr_path.read_text(errors="replace")
        except OSError:
            return ""

    # -- positions

    def set_positions(self, positions: dict[int, int]) -> float:
        """Put servos (by id) at raw positions by hand; they stop following the motion. Returns the
        time.monotonic() at which the change took effect (every later read sees it)."""
        return self.command("set", positions={str(i): int(v) for i, v in positions.items()})["t"]

    def set_action(self, action: dict[str, float]) -> float:
        """Like set_positions, in LeRobot's units: {"elbow_flex.pos": 20.0, "gripper.pos": 50.0}."""
        return self.set_positions(self.raw_of(action))

    def play(self, motion: dict | str | Path) -> float:
        """Start a motion now (a dict or file, see `load_motion`); the time.monotonic() it started at."""
        return self.command("motion", motion=load_motion(motion))["t"]

    def positions(self) -> dict[int, int]:
        """Present_Position of every servo now (raw)."""
        return {int(k): v for k, v in self.command("positions")["positions"].items()}

    def read(self, servo_id: int, register: str) -> int:
        """A register's value (signed as the servo encodes it), read without going through the bus."""
        return self.command("read", id=servo_id, register=register)["value"]

    def write(self, servo_id: int, register: str, value: int) -> None:
        """Set a register behind the host's back (not logged), e.g. to change a limit under LeRobot."""
        self.command("write", id=servo_id, register=register, value=int(value))

    # -- faults

    def unplug(self, ids=None) -> float:
        """Stop answering (all servos, or only `ids`), as when a cable is pulled; LeRobot then times out."""
        return self.command("unplug", ids=None if ids is None else [int(i) for i in ids])["t"]

    def unplug_at(self, instruction: str) -> None:
        """Stop answering (all servos) as the next packet of `instruction` ("ping", "read", "write", "sync_read")
        arrives, that packet included: a cable pulled at a known step of what the host does. `unplugged()` says
        when it happened; `replug()` ends it."""
        self.command("unplug_at", instruction=instruction)

    def unplugged(self) -> bool:
        """Whether the whole bus is silent now (`unplug()`, or `unplug_at()` reached)."""
        return bool(self.stats()["unplugged"])

    def replug(self, ids=None) -> float:
        """Answer again (the servos keep their registers, as on a data cable pulled with power kept)."""
        return self.command("replug", ids=None if ids is None else [int(i) for i in ids])["t"]

    def vanish(self) -> float:
        """Pull the USB adapter: the pty closes for good (its path disappears); the host's next read or write
        fails at the serial layer. There is no coming back: start a new emulator (a new port) instead."""
        return self.command("vanish")["t"]

    def corrupt(self, count: int = 1) -> None:
        """Send the next `count` status packets with a wrong checksum ("Incorrect status packet!")."""
        self.command("corrupt", count=int(count))

    # -- what the host did

    def writes(self) -> list[dict]:
        """Every register write so far: {"t", "id", "motor", "register", "value", "raw", "via"} in order."""
        try:
            text = self.log_path.read_text()
        except FileNotFoundError:
            return []
        return [json.loads(line) for line in text.splitlines() if line.endswith("}")]

    def goal_log(self) -> list[dict]:
        """Goal_Position writes (WRITE, SYNC_WRITE or REG_WRITE), `value` in raw steps.

        A SYNC_WRITE has no answer, so LeRobot's send_action returns before the emulator may have read it:
        read something through the bus first (get_observation), whose answer comes after, or wait_until."""
        return [w for w in self.writes() if w["register"] == "Goal_Position"]

    def torque_log(self) -> list[dict]:
        """Torque_Enable writes, `value` 1 or 0."""
        return [w for w in self.writes() if w["register"] == "Torque_Enable"]

    def stats(self) -> dict:
        """Packets received by instruction name ({"ping": 6, "sync_read": 12, ...}), bytes in/out, and "unplugged"."""
        return self.command("stats")

    # -- LeRobot's units and calibration files

    def motor_of(self, servo_id: int) -> tuple[str, ServoCalibration]:
        for motor, cal in self.calibration.items():
            if cal.id == servo_id:
                return motor, cal
        raise KeyError(f"no calibration for id {servo_id}")

    def raw_of(self, action: dict[str, float]) -> dict[int, int]:
        """{"elbow_flex.pos": value, ...} in LeRobot's units -> {id: raw}."""
        raw = {}
        for key, value in action.items():
            motor = key.removesuffix(".pos")
            cal = self.calibration[motor]
            raw[cal.id] = from_lerobot(value, cal, self.scale.mode(motor), self.scale.apply_drive_mode)
        return raw

    def action_of(self, raw: dict[int, float]) -> dict[str, float]:
        """{id: raw} -> {"elbow_flex.pos": value, ...} as LeRobot would report it."""
        out = {}
        for servo_id, value in raw.items():
            motor, cal = self.motor_of(servo_id)
            out[f"{motor}.pos"] = to_lerobot(value, cal, self.scale.mode(motor), self.scale.apply_drive_mode)
        return out

    def tolerance(self, motor: str) -> float:
        """One raw step of `motor` in LeRobot's units."""
        return step_of(self.calibration[motor], self.scale.mode(motor))

    def write_calibration_file(self, calibration_dir: Path, device_id: str, *, mismatch: bool = False) -> Path:
        """Write `calibration_dir/<device_id>.json` as LeRobot does, matching the servos' registers (so
        `connect(calibrate=False)` leaves `is_calibrated` True), or with `mismatch` one range off (False)."""
        calibration = mismatched(self.calibration) if mismatch else self.calibration
        return write_calibration_file(Path(calibration_dir) / f"{device_id}.json", calibration)

    # -- the end

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        """End the process (closing its pipe is enough; it is killed if it lingers)."""
        self._finalizer()

    def __enter__(self) -> ServoEmulator:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _stop_process(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        try:
            proc.stdin.close()
        except OSError:
            pass
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    for stream in (proc.stdin, proc.stdout):
        try:
            stream.close()
        except (OSError, ValueError):
            pass


class FeetechEmulator(ServoEmulator):
    """STS3215 servos (model 777) on Feetech protocol 0: an SO-100/SO-101 leader or follower."""

    protocol = "feetech"
    default_model = STS3215
    default_scale = SO_DEGREES
    default_calibration = SO101_CALIBRATION


class DynamixelEmulator(ServoEmulator):
    """XL330-M077 servos (model 1190) on Dynamixel protocol 2.0: a Koch leader."""

    protocol = "dynamixel"
    default_model = XL330_M077
    default_scale = KOCH_LEADER
    default_calibration = KOCH_CALIBRATION

    @classmethod
    def calibration_registers(cls, cal: ServoCalibration) -> dict[str, int]:
        return {**super().calibration_registers(cal), "Drive_Mode": cal.drive_mode}


# -- the child process ---------------------------------------------------------------------------------------


def host_baud_reader(fd: int):
    """() -> the bits/s the host last set on the pty (termios keeps it; Linux answers for the slave when asked on
    the master), or None for a rate termios cannot name."""
    speeds = {getattr(termios, name): int(name[1:]) for name in dir(termios) if name[:1] == "B" and name[1:].isdigit()}

    def read() -> int | None:
        try:
            return speeds.get(termios.tcgetattr(fd)[5])
        except termios.error:
            return None

    return read


def build_bus(config: dict, master: int, log_stream) -> FeetechBus | DynamixelBus:
    bus_class = FeetechBus if config["protocol"] == "feetech" else DynamixelBus
    defaults = STS3215_DEFAULTS if bus_class is FeetechBus else XL330_DEFAULTS
    follower = config["role"] == "follower"
    motion = Motion.from_dict(config["motion"]) if config.get("motion") else None
    now = time.monotonic()
    servos = {}
    for key, spec in config["servos"].items():
        servo = Servo(int(key), bus_class.table, follows_goal=follower, rate=config.get("rate"))
        for name, value in defaults.items():
            servo.put(name, value)
        servo.put("Model_Number", spec["model"])
        servo.put("ID", servo.id)
        servo.put("Baud_Rate", config["baud_register"])
        for name, value in spec["registers"].items():
            servo.put(name, value)
        servo.position = float(spec["position"])
        servo.put("Goal_Position", spec["position"])
        servo.motion, servo.motion_start = motion, now
        servo.update(now)
        servos[servo.id] = servo
    names = {int(k): v for k, v in config.get("names", {}).items()}
    return bus_class(servos, Log(log_stream, bus_class.table, names), host_baud_reader(master))


def control(bus, request: dict, counters: dict) -> dict:
    """One command from the test -> its answer."""
    op = request.get("op")
    now = time.monotonic()
    if op == "set":
        for key, raw in request["positions"].items():
            servo = bus.servos.get(int(key))
            if servo is None:
                return {"ok": False, "error": f"no servo with id {key}"}
            servo.hold(int(raw), now)
        return {"ok": True, "t": now}
    if op == "motion":
        motion = Motion.from_dict(request["motion"])
        for servo in bus.servos.values():
            servo.motion, servo.motion_start = motion, now
        return {"ok": True, "t": now}
    if op == "positions":
        for servo in bus.servos.values():
            servo.update(now)
        return {"ok": True, "positions": {s.id: s.get("Present_Position") for s in bus.servos.values()}}
    if op in ("read", "write"):
        servo = bus.servos.get(int(request["id"]))
        if servo is None or request["register"] not in bus.table:
            return {"ok": False, "error": f"no servo {request['id']} or register {request['register']!r}"}
        servo.update(now)
        if op == "write":
            servo.put(request["register"], request["value"])
            if request["register"] == "Present_Position":
                servo.hold(request["value"], now)
            return {"ok": True}
        return {"ok": True, "value": servo.get(request["register"])}
    if op in ("unplug", "replug"):
        if request.get("ids") is None:
            bus.unplugged = op == "unplug"
        else:
            for key in request["ids"]:
                if int(key) in bus.servos:
                    bus.servos[int(key)].present = op == "replug"
        return {"ok": True, "t": now}
    if op == "unplug_at":
        bus.unplug_at = str(request["instruction"])
        return {"ok": True}
    if op == "corrupt":
        bus.corrupt = int(request["count"])
        return {"ok": True}
    if op == "stats":
        return {"ok": True, "packets": dict(bus.counts), "unplugged": bus.unplugged, **counters}
    return {"ok": False, "error": f"unknown command {op!r}"}


def serve(config: dict) -> None:
    """The child's loop: answer the host on the pty's master, commands on stdin; return when stdin closes."""
    try:  # answer before the SDK's 34-50 ms timeouts even on a loaded machine (allowed for root only; best effort)
        os.nice(-10)
    except OSError:
        pass
    master, slave = os.openpty()
    tty.setraw(slave)  # no echo, no CR/LF translation: bytes pass unchanged both ways
    port = os.ttyname(slave)
    # Not held open here, so that the port looks free to `teleop devices` (which skips ports another process
    # holds); until the host opens it, reading the master fails with EIO, and the loop polls every 5 ms.
    os.close(slave)
    os.set_blocking(master, False)
    with open(config["log"], "a") as log_stream:
        bus = build_bus(config, master, log_stream)
        out = sys.stdout.buffer
        out.write((json.dumps({"ok": True, "port": port, "pid": os.getpid()}) + "\n").encode())
        out.flush()
        counters = {"bytes_in": 0, "bytes_out": 0}
        pending = b""
        stdin = sys.stdin.buffer.fileno()
        while True:
            ready = select.select([stdin] if master is None else [master, stdin], [], [], 1.0)[0]
            if master is not None and master in ready:
                try:
                    data = os.read(master, 65536)
                except BlockingIOError:
                    data = b""
                except OSError:  # EIO: no process has the port open
                    data = b""
                    ready = select.select([stdin], [], [], 0.005)[0]
                if data:
                    counters["bytes_in"] += len(data)
                    for reply in bus.feed(data):
                        try:
                            counters["bytes_out"] += os.write(master, reply)
                        except (BlockingIOError, OSError):
                            pass  # nobody reads the port: the bytes are lost, as on a wire
            if stdin in ready:
                chunk = os.read(stdin, 65536)
                if not chunk:
                    return  # the test closed the pipe or died
                pending += chunk
                while b"\n" in pending:
                    line, pending = pending.split(b"\n", 1)
                    try:
                        request = json.loads(line)
                        if request.get("op") == "vanish" and master is not None:
                            os.close(master)  # the pty goes away: its /dev/pts node too, as a USB adapter's would
                            master = None
                            answer = {"ok": True, "t": time.monotonic()}
                        else:
                            answer = control(bus, request, counters)
                    except Exception as exc:  # a bad command must not end the emulator
                        answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
                    out.write((json.dumps(answer) + "\n").encode())
                    out.flush()


if __name__ == "__main__":
    serve(json.loads(sys.argv[1]))
