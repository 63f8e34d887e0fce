"""Serial ports and the servos that answer on them, for `teleop devices`: which leader or follower arm is where.

Ports come from pyserial's `comports()` (with the /dev/serial/by-id name that points at each) plus any path
the user names (`--port`: a pty, or an adapter comports() misses). USB adapters and named ports are probed
with LeRobot's own motor buses (`FeetechMotorsBus`, `DynamixelMotorsBus`, the `hardware` extra), never with
a protocol of ours: a Feetech broadcast ping at 1,000,000 baud, then Dynamixel 2.0 at 1,000,000 and 57,600.
Each broadcast ping waits LeRobot's fixed ~0.8 s (1.4 s at 57,600), ports are probed side by side, and
LeRobot itself takes ~3 s to import, so it is imported only when there is a port to probe.
"""

from __future__ import annotations

import glob
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

HARDWARE_HINT = "probing for servos needs LeRobot: pip install 'mujoco-teleop[hardware]'"
DIALOUT_HINT = "permission denied: add your user to the dialout group (sudo usermod -aG dialout $USER, then log in again)"


def port_problem(port: str, what: str = "the arm") -> str | None:
    """Why this process cannot open the serial port `port` (one line), checked without opening it; None if it can.
    `what` names the device in the line ("the leader", "the follower")."""
    if not os.path.exists(port):
        return (f"no such serial port {port}: is {what} plugged in and powered? (`ls /dev/serial/by-id/` lists the USB "
                "serial devices; `lerobot-find-port` finds which one is the arm)")
    if not os.access(port, os.R_OK | os.W_OK):
        return f"{port}: {DIALOUT_HINT}"
    return None

# The ports a probe tries, in order: (protocol, baud rate). A bus speaks one protocol at one rate, so the
# first that finds servos ends the probe.
PROBES = (("feetech", 1_000_000), ("dynamixel", 1_000_000), ("dynamixel", 57_600))

GAP_FILL_UP_TO = 8  # ids a probe pings one by one where the broadcast ping missed them (arms use ids 1..6 or 7)

# LeRobot's arm types and the servos each needs by id (LeRobot model names); a bus that holds them fits.
_SO = {i: "sts3215" for i in range(1, 7)}
ARM_TYPES: tuple[tuple[str, str, dict[int, str]], ...] = (
    ("so100_leader", "feetech", _SO),
    ("so100_follower", "feetech", _SO),
    ("so101_leader", "feetech", _SO),
    ("so101_follower", "feetech", _SO),
    ("koch_leader", "dynamixel", {i: "xl330-m077" for i in range(1, 7)}),
    ("koch_follower", "dynamixel", {1: "xl430-w250", 2: "xl430-w250", **{i: "xl330-m288" for i in range(3, 7)}}),
)


@dataclass
class FoundServo:
    """One servo that answered a broadcast ping."""

    id: int
    model: str  # LeRobot's name for it ("sts3215", "xl330-m077"), or "model N" for a number LeRobot lacks
    model_number: int
    protocol: str  # "feetech" (protocol 0) or "dynamixel" (protocol 2.0)
    baudrate: int

    def to_dict(self) -> dict:
        return {"id": self.id, "model": self.model, "model_number": self.model_number, "protocol": self.protocol,
                "baudrate": self.baudrate}


@dataclass
class SerialPort:
    """One serial port: where it is, what answered on it, which LeRobot arm types that fits, or why not probed."""

    port: str
    by_id: str | None = None
    description: str = ""
    servos: list[FoundServo] = field(default_factory=list)
    fits: list[str] = field(default_factory=list)
    probed: bool = False
    problem: str | None = None  # why it was not probed, or what went wrong probing it

    def to_dict(self) -> dict:
        return {"port": self.port, "by_id": self.by_id, "description": self.description,
                "servos": [s.to_dict() for s in self.servos], "fits": self.fits, "probed": self.probed,
                "problem": self.problem}

    def summary(self) -> str:
        """One line: "6 STS3215 at ids 1-6 (feetech, 1000000 baud): fits so100_leader, ..." or why not."""
        if self.problem:
            return self.problem
        if not self.probed:
            return "not probed"
        if not self.servos:
            return "no servo answered (Feetech at 1000000 baud, Dynamixel 2.0 at 1000000 and 57600)"
        first = self.servos[0]
        counts: dict[str, int] = {}
        for servo in self.servos:
            counts[servo.model] = counts.get(servo.model, 0) + 1
        models = ", ".join(f"{n} {model.upper()}" for model, n in counts.items())
        text = f"{models} at ids {_ranges([s.id for s in self.servos])} ({first.protocol}, {first.baudrate} baud)"
        return text + (f": fits {', '.join(self.fits)}" if self.fits else ": no LeRobot arm type this project knows")


def _ranges(ids: list[int]) -> str:
    """[1, 2, 3, 5] -> "1-3, 5"."""
    out: list[str] = []
    for i in sorted(ids):
        if out and out[-1][1] == i - 1:
            out[-1] = (out[-1][0], i)
        else:
            out.append((i, i))
    return ", ".join(f"{a}-{b}" if b > a else str(a) for a, b in out)


def fits(servos: list[FoundServo]) -> list[str]:
    """The LeRobot arm types whose every motor (id and model) is among `servos`."""
    have = {(s.protocol, s.id): s.model for s in servos}
    return [name for name, protocol, needs in ARM_TYPES if all(have.get((protocol, i)) == m for i, m in needs.items())]


# -- finding ports ---------------------------------------------------------------------------------------------


def by_id_links() -> dict[str, str]:
    """{real device path: its /dev/serial/by-id link} (Linux names an adapter by its USB serial number there)."""
    links = {}
    for link in sorted(glob.glob("/dev/serial/by-id/*")):
        links.setdefault(os.path.realpath(link), link)
    return links


def listed_ports() -> list[SerialPort]:
    """The ports the system lists, USB adapters marked for probing (`probed` stays False until probed)."""
    links = by_id_links()
    ports: list[SerialPort] = []
    try:
        from serial.tools.list_ports import comports
    except ImportError:  # pyserial comes with the hardware extra; without it, the usual adapter names
        names = [p for pattern in ("/dev/ttyUSB*", "/dev/ttyACM*", "/dev/cu.usbmodem*", "/dev/cu.usbserial*")
                 for p in sorted(glob.glob(pattern))]
        return [SerialPort(p, links.get(os.path.realpath(p)), "USB serial") for p in names]
    for info in sorted(comports(), key=lambda i: i.device):
        usb = info.vid is not None
        description = info.description if info.description not in (None, "n/a") else ""
        port = SerialPort(info.device, links.get(os.path.realpath(info.device)), description)
        if not usb:
            port.problem = "not probed: not a USB serial adapter (name it with --port to probe it)"
        ports.append(port)
    return ports


def holders(path: str) -> list[str]:
    """Other processes (of this user) that have `path` open, as "PID (name)": pinging would disturb them."""
    target = os.path.realpath(path)
    found = []
    if not os.path.isdir("/proc"):
        return found
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            fds = os.scandir(f"/proc/{entry.name}/fd")
            with fds:
                if any(os.readlink(fd.path) == target for fd in fds):
                    with open(f"/proc/{entry.name}/comm") as f:
                        found.append(f"{entry.name} ({f.read().strip()})")
        except OSError:
            continue
    return found


def open_problem(path: str) -> str | None:
    """Why `path` cannot be probed (one line), or None if it can."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except PermissionError:
        return DIALOUT_HINT if sys.platform.startswith("linux") else "permission denied"
    except FileNotFoundError:
        return "no such device (unplugged?)"
    except OSError as exc:
        if exc.errno == 16:  # EBUSY: opened exclusively by another program
            return "busy: another program has it open exclusively"
        return f"cannot open: {exc.strerror or exc}"
    try:
        import fcntl

        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # pyserial's exclusive mode holds this lock
        fcntl.flock(fd, fcntl.LOCK_UN)
    except OSError:
        return "busy: another program holds its lock"
    finally:
        os.close(fd)
    others = holders(path)
    if others:
        return f"busy: in use by {', '.join(others)}; not probed (pings would disturb it)"
    return None


# -- probing through LeRobot -----------------------------------------------------------------------------------


def _bus_classes() -> dict[str, type] | None:
    try:
        import dynamixel_sdk  # noqa: F401 - LeRobot's buses need these SDKs (its feetech and dynamixel extras)
        import scservo_sdk  # noqa: F401
        from lerobot.motors.dynamixel import DynamixelMotorsBus
        from lerobot.motors.feetech import FeetechMotorsBus
    except ImportError:
        return None
    return {"feetech": FeetechMotorsBus, "dynamixel": DynamixelMotorsBus}


def ping_bus(bus_class: type, path: str, protocol: str, baudrate: int) -> list[FoundServo]:
    """Broadcast-ping `path` at `baudrate` with LeRobot's bus class; the servos that answered."""
    bus = bus_class(path, {})
    bus.connect(handshake=False)
    try:
        bus.set_baudrate(baudrate)
        answered = bus.broadcast_ping() or {}
        if answered:
            # LeRobot drops, without a word, a servo whose answer came after its 34-50 ms timeout (a loaded
            # machine): ping each missing id up to one past the highest found (at most GAP_FILL_UP_TO) again.
            for servo_id in range(1, min(max(answered) + 1, GAP_FILL_UP_TO) + 1):
                if servo_id not in answered:
                    number = bus.ping(servo_id, num_retry=1)
                    if number is not None:
                        answered[servo_id] = number
    finally:
        bus.disconnect(disable_torque=False)
    names = {number: name for name, number in bus_class.model_number_table.items()}
    return [FoundServo(i, names.get(n, f"model {n}"), n, protocol, baudrate) for i, n in sorted(answered.items())]


def probe(port: SerialPort, buses: dict[str, type]) -> SerialPort:
    """Fill `port.servos` and `port.fits` (or `port.problem`) by pinging it through LeRobot."""
    try:
        for protocol, baudrate in PROBES:
            port.servos = ping_bus(buses[protocol], port.port, protocol, baudrate)
            if port.servos:
                break
    except Exception as exc:  # LeRobot's ConnectionError, pyserial's SerialException, OSError: one line
        cause = exc.__cause__ or exc
        port.problem = f"probe failed: {str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__}"
        return port
    port.probed = True
    port.fits = fits(port.servos)
    return port


def serial_ports(extra: list[str] | tuple[str, ...] = ()) -> tuple[list[SerialPort], str | None]:
    """Every serial port, with its servos where it was probed, and a note for the whole list (None if none):
    the USB adapters the system lists and every path in `extra` are probed."""
    ports = listed_ports()
    known = {os.path.realpath(p.port): p for p in ports}
    for path in extra:
        found = known.get(os.path.realpath(path))
        if found is None:
            found = SerialPort(path, by_id_links().get(os.path.realpath(path)), "named with --port")
            ports.append(found)
            known[os.path.realpath(path)] = found
        found.problem = None  # named: probe it whatever it is
    for port in ports:
        if port.problem is None:
            port.problem = open_problem(port.port)  # before importing LeRobot (~3 s): maybe none is left to probe
    to_probe = [p for p in ports if p.problem is None]
    if not to_probe:
        return ports, None
    buses = _bus_classes()
    if buses is None:
        for port in to_probe:
            port.problem = "not probed: LeRobot and its servo SDKs are not installed"
        return ports, HARDWARE_HINT
    with ThreadPoolExecutor(max_workers=min(8, len(to_probe))) as pool:
        list(pool.map(lambda p: probe(p, buses), to_probe))
    return ports, None
