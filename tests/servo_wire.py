"""Servo register memory and the two serial wire protocols, byte for byte, as the servo side of the bus.

Runs inside the emulator's own process (tests/servo_emulator.py starts it): `FeetechBus` answers Feetech SCS
protocol 0 (STS3215: SO-100/SO-101 arms), `DynamixelBus` answers Dynamixel protocol 2.0 (XL330/XL430: Koch
arms). Each takes the bytes the host wrote (`feed`) and returns the status packets the servos send back. Written
from the servo makers' public packet descriptions; no SDK or LeRobot code is imported here.

Positions are raw encoder steps (0..4095 a turn) as the Present_Position register reads, i.e. after the servo
applies its Homing_Offset: the emulator stores a homing offset but does not shift positions by it.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import IO

BROADCAST = 0xFE

# -- register tables: name -> (address, size in bytes, sign encoding) ---------------------------------------
# Sign encoding: None (unsigned), ("sm", bit) sign-magnitude with the sign in `bit` (Feetech), "2c" two's
# complement over the register's size (Dynamixel).

STS3215_REGISTERS: dict[str, tuple[int, int, object]] = {
    "Firmware_Major_Version": (0, 1, None),
    "Firmware_Minor_Version": (1, 1, None),
    "Model_Number": (3, 2, None),
    "ID": (5, 1, None),
    "Baud_Rate": (6, 1, None),
    "Return_Delay_Time": (7, 1, None),
    "Response_Status_Level": (8, 1, None),
    "Min_Position_Limit": (9, 2, None),
    "Max_Position_Limit": (11, 2, None),
    "Max_Temperature_Limit": (13, 1, None),
    "Max_Voltage_Limit": (14, 1, None),
    "Min_Voltage_Limit": (15, 1, None),
    "Max_Torque_Limit": (16, 2, None),
    "Phase": (18, 1, None),
    "Unloading_Condition": (19, 1, None),
    "LED_Alarm_Condition": (20, 1, None),
    "P_Coefficient": (21, 1, None),
    "D_Coefficient": (22, 1, None),
    "I_Coefficient": (23, 1, None),
    "Minimum_Startup_Force": (24, 2, None),
    "CW_Dead_Zone": (26, 1, None),
    "CCW_Dead_Zone": (27, 1, None),
    "Protection_Current": (28, 2, None),
    "Angular_Resolution": (30, 1, None),
    "Homing_Offset": (31, 2, ("sm", 11)),
    "Operating_Mode": (33, 1, None),
    "Protective_Torque": (34, 1, None),
    "Protection_Time": (35, 1, None),
    "Overload_Torque": (36, 1, None),
    "Torque_Enable": (40, 1, None),
    "Acceleration": (41, 1, None),
    "Goal_Position": (42, 2, ("sm", 15)),
    "Goal_Time": (44, 2, None),
    "Goal_Velocity": (46, 2, ("sm", 15)),
    "Torque_Limit": (48, 2, None),
    "Lock": (55, 1, None),
    "Present_Position": (56, 2, ("sm", 15)),
    "Present_Velocity": (58, 2, ("sm", 15)),
    "Present_Load": (60, 2, ("sm", 10)),
    "Present_Voltage": (62, 1, None),
    "Present_Temperature": (63, 1, None),
    "Status": (65, 1, None),
    "Moving": (66, 1, None),
    "Present_Current": (69, 2, None),
    "Maximum_Acceleration": (85, 1, None),
}

# Power-on values of an STS3215 (model 777) as shipped, besides ID and model, which the emulator sets.
STS3215_DEFAULTS = {
    "Firmware_Major_Version": 3, "Firmware_Minor_Version": 10, "Baud_Rate": 0, "Return_Delay_Time": 250,
    "Response_Status_Level": 1, "Min_Position_Limit": 0, "Max_Position_Limit": 4095, "Max_Temperature_Limit": 70,
    "Max_Voltage_Limit": 140, "Min_Voltage_Limit": 40, "Max_Torque_Limit": 1000, "Phase": 12,
    "Unloading_Condition": 44, "LED_Alarm_Condition": 47, "P_Coefficient": 32, "D_Coefficient": 32,
    "I_Coefficient": 0, "Minimum_Startup_Force": 16, "CW_Dead_Zone": 1, "CCW_Dead_Zone": 1,
    "Protection_Current": 500, "Angular_Resolution": 1, "Operating_Mode": 0, "Protective_Torque": 20,
    "Protection_Time": 200, "Overload_Torque": 80, "Torque_Limit": 1000, "Present_Voltage": 74,
    "Present_Temperature": 28, "Maximum_Acceleration": 0,
}

# Feetech Baud_Rate register value -> bits per second.
FEETECH_BAUDS = {0: 1_000_000, 1: 500_000, 2: 250_000, 3: 128_000, 4: 115_200, 5: 57_600, 6: 38_400, 7: 19_200}

XL330_REGISTERS: dict[str, tuple[int, int, object]] = {
    "Model_Number": (0, 2, None),
    "Model_Information": (2, 4, None),
    "Firmware_Version": (6, 1, None),
    "ID": (7, 1, None),
    "Baud_Rate": (8, 1, None),
    "Return_Delay_Time": (9, 1, None),
    "Drive_Mode": (10, 1, None),
    "Operating_Mode": (11, 1, None),
    "Secondary_ID": (12, 1, None),
    "Protocol_Type": (13, 1, None),
    "Homing_Offset": (20, 4, "2c"),
    "Moving_Threshold": (24, 4, None),
    "Temperature_Limit": (31, 1, None),
    "Max_Voltage_Limit": (32, 2, None),
    "Min_Voltage_Limit": (34, 2, None),
    "PWM_Limit": (36, 2, None),
    "Current_Limit": (38, 2, None),
    "Acceleration_Limit": (40, 4, None),
    "Velocity_Limit": (44, 4, None),
    "Max_Position_Limit": (48, 4, None),
    "Min_Position_Limit": (52, 4, None),
    "Shutdown": (63, 1, None),
    "Torque_Enable": (64, 1, None),
    "LED": (65, 1, None),
    "Status_Return_Level": (68, 1, None),
    "Registered_Instruction": (69, 1, None),
    "Hardware_Error_Status": (70, 1, None),
    "Velocity_I_Gain": (76, 2, None),
    "Velocity_P_Gain": (78, 2, None),
    "Position_D_Gain": (80, 2, None),
    "Position_I_Gain": (82, 2, None),
    "Position_P_Gain": (84, 2, None),
    "Bus_Watchdog": (98, 1, None),
    "Goal_PWM": (100, 2, "2c"),
    "Goal_Current": (102, 2, "2c"),
    "Goal_Velocity": (104, 4, "2c"),
    "Profile_Acceleration": (108, 4, None),
    "Profile_Velocity": (112, 4, None),
    "Goal_Position": (116, 4, "2c"),
    "Realtime_Tick": (120, 2, None),
    "Moving": (122, 1, None),
    "Moving_Status": (123, 1, None),
    "Present_PWM": (124, 2, "2c"),
    "Present_Current": (126, 2, "2c"),
    "Present_Velocity": (128, 4, "2c"),
    "Present_Position": (132, 4, "2c"),
    "Present_Input_Voltage": (144, 2, None),
    "Present_Temperature": (146, 1, None),
}

XL330_DEFAULTS = {
    "Firmware_Version": 46, "Baud_Rate": 3, "Return_Delay_Time": 250, "Drive_Mode": 0, "Operating_Mode": 3,
    "Protocol_Type": 2, "Moving_Threshold": 10, "Temperature_Limit": 70, "Max_Voltage_Limit": 70,
    "Min_Voltage_Limit": 35, "PWM_Limit": 885, "Current_Limit": 1750, "Velocity_Limit": 445,
    "Max_Position_Limit": 4095, "Min_Position_Limit": 0, "Shutdown": 52, "Status_Return_Level": 2,
    "Position_P_Gain": 400, "Velocity_I_Gain": 1000, "Velocity_P_Gain": 100, "Present_Input_Voltage": 50,
    "Present_Temperature": 28,
}

# Dynamixel X-series Baud_Rate register value -> bits per second.
DYNAMIXEL_BAUDS = {0: 9_600, 1: 57_600, 2: 115_200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000}
DYNAMIXEL_EEPROM_END = 64  # addresses below this refuse writes while torque is on (access error)


def encode(value: int, size: int, sign: object) -> int:
    """A signed value as the unsigned register content."""
    if sign == "2c":
        return value & ((1 << (8 * size)) - 1)
    if isinstance(sign, tuple):
        bit = sign[1]
        return (-value | (1 << bit)) if value < 0 else value
    return value


def decode(raw: int, size: int, sign: object) -> int:
    """The unsigned register content as the signed value it stands for."""
    if sign == "2c":
        top = 1 << (8 * size - 1)
        return raw - (1 << (8 * size)) if raw & top else raw
    if isinstance(sign, tuple):
        bit = sign[1]
        return -(raw & ~(1 << bit)) if raw & (1 << bit) else raw
    return raw


# -- one servo: its memory and where its shaft is ------------------------------------------------------------


@dataclass
class Motion:
    """A recorded motion: times in seconds from its start and raw positions per id; loops or holds the end."""

    times: list[float]
    positions: dict[int, list[int]]
    loop: bool = True

    @classmethod
    def from_dict(cls, data: dict) -> Motion:
        times = [float(t) for t in data["t"]]
        positions = {int(k): [int(round(v)) for v in vals] for k, vals in data["positions"].items()}
        for key, vals in positions.items():
            if len(vals) != len(times):
                raise ValueError(f"motion: id {key} has {len(vals)} positions for {len(times)} times")
        if any(b <= a for a, b in zip(times, times[1:])):
            raise ValueError("motion: times must increase")
        return cls(times, positions, bool(data.get("loop", True)))

    def at(self, servo_id: int, t: float) -> int | None:
        """Raw position of `servo_id` `t` seconds after the start (linear between samples); None if not in it."""
        values = self.positions.get(servo_id)
        if values is None:
            return None
        times = self.times
        if len(times) == 1 or t <= times[0]:
            return values[0]
        span = times[-1] - times[0]
        if t >= times[-1]:
            if not self.loop or span <= 0:
                return values[-1]
            t = times[0] + (t - times[0]) % span
        lo, hi = 0, len(times) - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if times[mid] <= t:
                lo = mid
            else:
                hi = mid
        frac = (t - times[lo]) / (times[hi] - times[lo])
        return int(round(values[lo] + frac * (values[hi] - values[lo])))


@dataclass
class Servo:
    """One servo: 256 bytes of register memory and the state behind Present_Position.

    A leader's shaft is where the hand (motion or `set`) put it; a follower's also moves toward its
    Goal_Position while torque is on, at `rate` raw steps per second (None: at once).
    """

    id: int
    table: dict[str, tuple[int, int, object]]
    follows_goal: bool
    rate: float | None
    mem: bytearray = field(default_factory=lambda: bytearray(256))
    position: float = 2048.0
    motion: Motion | None = None
    motion_start: float = 0.0
    goal: int | None = None
    updated: float = field(default_factory=time.monotonic)
    present: bool = True  # False: unplugged (answers nothing)
    pending: tuple[int, bytes] | None = None  # REG_WRITE waiting for ACTION

    def get(self, name: str) -> int:
        addr, size, sign = self.table[name]
        return decode(int.from_bytes(self.mem[addr:addr + size], "little"), size, sign)

    def put(self, name: str, value: int) -> None:
        addr, size, sign = self.table[name]
        self.mem[addr:addr + size] = encode(int(value), size, sign).to_bytes(size, "little")

    def update(self, now: float) -> None:
        """Advance the shaft to `now` and write it into Present_Position (and Moving)."""
        moving = 0
        if self.motion is not None:
            raw = self.motion.at(self.id, now - self.motion_start)
            if raw is not None:
                moving = int(raw != round(self.position))
                self.position = float(raw)
        if self.follows_goal and self.goal is not None and self.get("Torque_Enable"):
            gap = self.goal - self.position
            if gap:
                step = abs(gap) if self.rate is None else min(abs(gap), self.rate * max(0.0, now - self.updated))
                self.position += step if gap > 0 else -step
                moving = int(round(self.position) != self.goal)
        self.updated = now
        self.put("Present_Position", int(round(self.position)))
        if "Moving" in self.table:
            self.put("Moving", moving)

    def hold(self, raw: int, now: float) -> None:
        """Put the shaft at `raw` by hand: the motion no longer drives this servo."""
        self.update(now)
        self.motion = None
        self.position = float(raw)
        self.put("Present_Position", int(raw))


class Log:
    """Register writes as JSON lines (t: time.monotonic(), id, register, value, via), flushed at once."""

    def __init__(self, stream: IO[str] | None, table: dict[str, tuple[int, int, object]], names: dict[int, str]):
        self.stream = stream
        self.by_address = {addr: (name, size, sign) for name, (addr, size, sign) in table.items()}
        self.names = names

    def writes(self, servo: Servo, address: int, length: int, via: str, now: float) -> None:
        if self.stream is None:
            return
        for addr in range(address, address + length):
            entry = self.by_address.get(addr)
            if entry is None:
                continue
            name, size, sign = entry
            raw = int.from_bytes(servo.mem[addr:addr + size], "little")
            row = {"t": now, "id": servo.id, "register": name, "value": decode(raw, size, sign), "raw": raw, "via": via}
            if servo.id in self.names:
                row["motor"] = self.names[servo.id]
            self.stream.write(json.dumps(row) + "\n")
        self.stream.flush()


# -- the bus: shared by both protocols -----------------------------------------------------------------------


class ServoBus:
    """The servos on one bus and what every protocol does with them; subclasses frame the bytes."""

    table: dict[str, tuple[int, int, object]]
    bauds: dict[int, int]

    def __init__(self, servos: dict[int, Servo], log: Log, host_baud=lambda: None) -> None:
        self.servos = servos
        self.log = log
        self.host_baud = host_baud  # () -> the bits/s the host set on the port, or None if unknown
        self.buffer = bytearray()
        self.buffer_since = 0.0
        self.corrupt = 0  # this many next status packets go out with a wrong checksum
        self.unplugged = False
        self.unplug_at: str | None = None  # an instruction name: the bus goes silent as the next such packet arrives
        self.counts: dict[str, int] = {}

    def listening(self, servo_id: int) -> list[Servo]:
        """The servos that hear a packet for `servo_id` (all for broadcast): plugged in, at the host's baud rate."""
        if self.unplugged:
            return []
        baud = self.host_baud()
        found = self.servos.values() if servo_id == BROADCAST else [s for s in self.servos.values() if s.id == servo_id]
        return [s for s in found if s.present and (baud is None or self.bauds.get(s.get("Baud_Rate")) == baud)]

    def feed(self, data: bytes) -> list[bytes]:
        """Bytes from the host -> the status packets to send back (in order)."""
        now = time.monotonic()
        if self.buffer and now - self.buffer_since > 0.02:
            self.buffer.clear()  # a partial packet older than 20 ms is line noise: servos time it out too
        if not self.buffer:
            self.buffer_since = now
        self.buffer += data
        replies: list[bytes] = []
        while True:
            packet = self.take_packet()
            if packet is None:
                break
            servo_id, instruction, params = packet
            name = self.instruction_names.get(instruction, f"0x{instruction:02x}")
            self.counts[name] = self.counts.get(name, 0) + 1
            if self.unplug_at == name:  # a cable pulled just as the host got here: this packet goes unanswered
                self.unplugged, self.unplug_at = True, None
            for reply in self.handle(servo_id, instruction, params, time.monotonic()):
                if self.corrupt > 0:
                    self.corrupt -= 1
                    reply = reply[:-1] + bytes([reply[-1] ^ 0x5A])
                replies.append(reply)
        if not self.buffer:
            self.buffer_since = now
        return replies

    instruction_names = {1: "ping", 2: "read", 3: "write", 4: "reg_write", 5: "action", 0x82: "sync_read", 0x83: "sync_write",
                         0x92: "bulk_read", 0x93: "bulk_write", 6: "reset", 8: "reboot", 0x10: "clear"}

    def take_packet(self) -> tuple[int, int, bytes] | None:
        raise NotImplementedError

    def status(self, servo: Servo, error: int, params: bytes) -> bytes:
        raise NotImplementedError

    def read(self, servo: Servo, address: int, length: int, now: float) -> bytes:
        servo.update(now)
        return bytes(servo.mem[address:address + length]).ljust(length, b"\0")

    def write(self, servo: Servo, address: int, data: bytes, via: str, now: float) -> int:
        """Store `data` at `address`; the error byte to answer with (0: done)."""
        servo.update(now)
        old_id = servo.id
        servo.mem[address:address + len(data)] = data[: max(0, 256 - address)]
        goal_addr, goal_size, _ = self.table["Goal_Position"]
        if address <= goal_addr < address + len(data):
            servo.goal = servo.get("Goal_Position")
        self.log.writes(servo, address, len(data), via, now)
        id_addr = self.table["ID"][0]
        if address <= id_addr < address + len(data) and servo.mem[id_addr] != old_id:
            self.servos.pop(old_id, None)
            servo.id = servo.mem[id_addr]
            self.servos[servo.id] = servo
        servo.update(now)
        return 0

    def handle(self, servo_id: int, instruction: int, params: bytes, now: float) -> list[bytes]:
        raise NotImplementedError


class FeetechBus(ServoBus):
    """Feetech SCS protocol 0: `FF FF ID LEN INSTR PARAMS CHECKSUM`, LEN = len(PARAMS) + 2,
    CHECKSUM = ~(ID + LEN + INSTR + sum(PARAMS)) & 0xFF; the status packet has the error byte in INSTR's place."""

    table = STS3215_REGISTERS
    bauds = FEETECH_BAUDS

    @staticmethod
    def checksum(body: bytes) -> int:
        return ~sum(body) & 0xFF

    def take_packet(self) -> tuple[int, int, bytes] | None:
        buf = self.buffer
        while True:
            start = buf.find(b"\xff\xff")
            if start < 0:
                del buf[: max(0, len(buf) - 1)]
                return None
            del buf[:start]
            if len(buf) < 4:
                return None
            servo_id, length = buf[2], buf[3]
            if servo_id == 0xFF or length < 2:
                del buf[0]
                continue
            if len(buf) < 4 + length:
                return None
            packet = bytes(buf[: 4 + length])
            if self.checksum(packet[2:-1]) != packet[-1]:
                del buf[0]  # not a packet after all: look for the next header
                continue
            del buf[: 4 + length]
            return servo_id, packet[4], packet[5:-1]

    def status(self, servo: Servo, error: int, params: bytes) -> bytes:
        body = bytes([servo.id, len(params) + 2, error]) + params
        return b"\xff\xff" + body + bytes([self.checksum(body)])

    def handle(self, servo_id: int, instruction: int, params: bytes, now: float) -> list[bytes]:
        targets = self.listening(servo_id)
        answer = servo_id != BROADCAST
        replies = []
        if instruction == 1:  # PING; broadcast ping: every servo answers
            return [self.status(s, 0, b"") for s in sorted(targets, key=lambda s: s.id)]
        if instruction == 2 and len(params) >= 2:  # READ addr len
            return [self.status(s, 0, self.read(s, params[0], params[1], now)) for s in targets if answer]
        if instruction == 3 and params:  # WRITE addr data...
            for s in targets:
                error = self.write(s, params[0], params[1:], "write", now)
                if answer:
                    replies.append(self.status(s, error, b""))
            return replies
        if instruction == 4 and params:  # REG_WRITE: held until ACTION
            for s in targets:
                s.pending = (params[0], bytes(params[1:]))
                if answer:
                    replies.append(self.status(s, 0, b""))
            return replies
        if instruction == 5:  # ACTION
            for s in targets:
                if s.pending is not None:
                    self.write(s, s.pending[0], s.pending[1], "reg_write", now)
                    s.pending = None
                if answer:
                    replies.append(self.status(s, 0, b""))
            return replies
        if instruction == 0x82 and len(params) >= 2:  # SYNC_READ addr len ids...: each listed servo answers in turn
            address, length = params[0], params[1]
            for wanted in params[2:]:
                for s in self.listening(wanted):
                    replies.append(self.status(s, 0, self.read(s, address, length, now)))
            return replies
        if instruction == 0x83 and len(params) >= 2:  # SYNC_WRITE addr len (id data*len)*: nobody answers
            address, length = params[0], params[1]
            chunk = params[2:]
            for i in range(0, len(chunk) - length, length + 1):
                for s in self.listening(chunk[i]):
                    self.write(s, address, chunk[i + 1: i + 1 + length], "sync_write", now)
            return []
        if instruction in (6, 8) and answer:  # RESET, RESTART: acknowledged, memory kept
            return [self.status(s, 0, b"") for s in targets]
        return []


class DynamixelBus(ServoBus):
    """Dynamixel protocol 2.0: `FF FF FD 00 ID LEN_L LEN_H INSTR PARAMS CRC_L CRC_H`, LEN = len(PARAMS) + 3,
    CRC-16 (polynomial 0x8005) over everything before it, and `FD` stuffed after every `FF FF FD` in
    INSTR..PARAMS. A status packet is INSTR 0x55, then the error byte, then its parameters."""

    table = XL330_REGISTERS
    bauds = DYNAMIXEL_BAUDS
    _crc_table: list[int] = []

    @classmethod
    def crc(cls, data: bytes) -> int:
        if not cls._crc_table:
            for byte in range(256):
                value = byte << 8
                for _ in range(8):
                    value = ((value << 1) ^ 0x8005) if value & 0x8000 else value << 1
                cls._crc_table.append(value & 0xFFFF)
        acc = 0
        for byte in data:
            acc = ((acc << 8) ^ cls._crc_table[((acc >> 8) ^ byte) & 0xFF]) & 0xFFFF
        return acc

    def take_packet(self) -> tuple[int, int, bytes] | None:
        buf = self.buffer
        while True:
            start = buf.find(b"\xff\xff\xfd")
            if start < 0:
                del buf[: max(0, len(buf) - 2)]
                return None
            del buf[:start]
            if len(buf) < 7:
                return None
            length = buf[5] | (buf[6] << 8)
            if buf[3] != 0x00 or length < 3 or length > 1024:
                del buf[0]
                continue
            if len(buf) < 7 + length:
                return None
            packet = bytes(buf[: 7 + length])
            if self.crc(packet[:-2]) != packet[-2] | (packet[-1] << 8):
                del buf[0]
                continue
            del buf[: 7 + length]
            body = packet[7:-2].replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")
            return packet[4], body[0], body[1:]

    def status(self, servo: Servo, error: int, params: bytes) -> bytes:
        body = (bytes([0x55, error]) + params).replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")
        head = bytes([0xFF, 0xFF, 0xFD, 0x00, servo.id]) + (len(body) + 2).to_bytes(2, "little")
        packet = head + body
        return packet + self.crc(packet).to_bytes(2, "little")

    def write(self, servo: Servo, address: int, data: bytes, via: str, now: float) -> int:
        if address < DYNAMIXEL_EEPROM_END and servo.get("Torque_Enable"):
            return 7  # access error: the EEPROM area is locked while torque is on
        return super().write(servo, address, data, via, now)

    def handle(self, servo_id: int, instruction: int, params: bytes, now: float) -> list[bytes]:
        targets = self.listening(servo_id)
        answer = servo_id != BROADCAST
        replies = []

        def word(i: int) -> int:
            return params[i] | (params[i + 1] << 8)

        if instruction == 1:  # PING: model number, firmware
            return [self.status(s, 0, bytes(s.mem[0:2]) + bytes([s.get("Firmware_Version")]))
                    for s in sorted(targets, key=lambda s: s.id)]
        if instruction == 2 and len(params) >= 4:  # READ addr(2) len(2)
            return [self.status(s, 0, self.read(s, word(0), word(2), now)) for s in targets if answer]
        if instruction in (3, 4) and len(params) >= 2:  # WRITE / REG_WRITE addr(2) data...
            for s in targets:
                if instruction == 3:
                    error = self.write(s, word(0), params[2:], "write", now)
                else:
                    s.pending, error = (word(0), bytes(params[2:])), 0
                if answer:
                    replies.append(self.status(s, error, b""))
            return replies
        if instruction == 5:  # ACTION
            for s in targets:
                if s.pending is not None:
                    self.write(s, s.pending[0], s.pending[1], "reg_write", now)
                    s.pending = None
            return []
        if instruction == 0x82 and len(params) >= 4:  # SYNC_READ addr(2) len(2) ids...
            for wanted in params[4:]:
                for s in self.listening(wanted):
                    replies.append(self.status(s, 0, self.read(s, word(0), word(2), now)))
            return replies
        if instruction == 0x92:  # BULK_READ (id addr(2) len(2))*
            for i in range(0, len(params) - 4, 5):
                for s in self.listening(params[i]):
                    replies.append(self.status(s, 0, self.read(s, word(i + 1), word(i + 3), now)))
            return replies
        if instruction == 0x83 and len(params) >= 4:  # SYNC_WRITE addr(2) len(2) (id data*len)*
            address, length = word(0), word(2)
            chunk = params[4:]
            for i in range(0, len(chunk) - length, length + 1):
                for s in self.listening(chunk[i]):
                    self.write(s, address, chunk[i + 1: i + 1 + length], "sync_write", now)
            return []
        if instruction == 0x93:  # BULK_WRITE (id addr(2) len(2) data*len)*
            i = 0
            while i + 5 <= len(params):
                length = word(i + 3)
                for s in self.listening(params[i]):
                    self.write(s, word(i + 1), params[i + 5: i + 5 + length], "bulk_write", now)
                i += 5 + length
            return []
        if instruction in (6, 8, 0x10) and answer:  # FACTORY_RESET, REBOOT, CLEAR: acknowledged
            return [self.status(s, 0, b"") for s in targets]
        return []
