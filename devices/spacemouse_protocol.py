"""3Dconnexion SpaceMouse HID reports, as pure functions (no I/O, no threads).

Kept apart from the reading thread so that the byte layouts, the deadzone and
the axis mapping can be checked on exact report bytes without hardware.

Report layouts (each report starts with its report id byte):
- separate: id 1 = x, y, z and id 2 = rx, ry, rz, three int16 little-endian each
  (7 bytes); SpaceNavigator, SpaceMouse Compact, SpaceMouse Pro, SpaceExplorer,
  SpacePilot and the other older models.
- combined: id 1 = x, y, z, rx, ry, rz in one 13-byte report; SpaceMouse Wireless,
  Pro Wireless, Enterprise, Universal Receiver.
- id 3 = buttons bitmask (bit 0 left, bit 1 right) on both.
The layout is told apart by the report length, so an unknown product id still
parses. Raw values span about +-350. HID axes: x to the operator's right,
y toward the operator, z down; rotations are right-handed about those axes.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

FULL_SCALE = 350.0  # raw counts at full deflection (devices reach ~350, some a bit more)

VENDOR_3DCONNEXION = 0x256F
VENDOR_LOGITECH = 0x046D  # older 3Dconnexion models were sold under Logitech's id

# Logitech's id covers thousands of unrelated products: list the 3Dconnexion ones.
LOGITECH_ERA_MODELS: dict[int, str] = {
    0xC603: "SpaceMouse Plus XT",
    0xC605: "CadMan",
    0xC606: "SpaceMouse Classic",
    0xC621: "SpaceBall 5000",
    0xC623: "SpaceTraveler",
    0xC625: "SpacePilot",
    0xC626: "SpaceNavigator",
    0xC627: "SpaceExplorer",
    0xC628: "SpaceNavigator for Notebooks",
    0xC629: "SpacePilot Pro",
    0xC62B: "SpaceMouse Pro",
}

# 3Dconnexion's own id: the 6-DoF models by name; anything else is accepted
# unless it is one of the non-6-DoF products below.
MODELS_3DCONNEXION: dict[int, str] = {
    0xC62E: "SpaceMouse Wireless (cable)",
    0xC62F: "SpaceMouse Wireless (receiver)",
    0xC631: "SpaceMouse Pro Wireless (cable)",
    0xC632: "SpaceMouse Pro Wireless (receiver)",
    0xC633: "SpaceMouse Enterprise",
    0xC635: "SpaceMouse Compact",
    0xC636: "SpaceMouse Module",
    0xC638: "SpaceMouse Pro Wireless BT",
    0xC63A: "SpaceMouse Wireless BT",
    0xC652: "Universal Receiver",
}
NOT_6DOF_3DCONNEXION: frozenset[int] = frozenset(
    {
        0xC650,  # CadMouse
        0xC651,  # CadMouse Wireless
        0xC654,  # CadMouse Pro Wireless
        0xC655,  # CadMouse Compact
        0xC656,  # CadMouse Pro Wireless Left
        0xC657,  # CadMouse Compact Wireless
        0xC658,  # CadMouse Pro
        0xC664,  # Keyboard Pro
        0xC665,  # Numpad Pro
    }
)

USAGE_PAGE_GENERIC_DESKTOP = 0x01
USAGE_MULTI_AXIS_CONTROLLER = 0x08


def is_spacemouse(vendor_id: int, product_id: int, usage_page: int = 0, usage: int = 0) -> bool:
    """True for a 3Dconnexion 6-DoF device (or its receiver's 6-DoF interface).

    usage_page/usage are 0 when the HID backend could not read them; then only
    the ids decide.
    """
    if usage_page and (usage_page, usage) != (USAGE_PAGE_GENERIC_DESKTOP, USAGE_MULTI_AXIS_CONTROLLER):
        return False
    if vendor_id == VENDOR_3DCONNEXION:
        return product_id not in NOT_6DOF_3DCONNEXION
    if vendor_id == VENDOR_LOGITECH:
        return product_id in LOGITECH_ERA_MODELS
    return False


def model_name(vendor_id: int, product_id: int) -> str:
    """A readable model name, or the ids when the model is not in our tables."""
    table = MODELS_3DCONNEXION if vendor_id == VENDOR_3DCONNEXION else LOGITECH_ERA_MODELS
    return table.get(product_id, f"3Dconnexion device {vendor_id:04x}:{product_id:04x}")


@dataclass
class RawState:
    """Last raw values seen: 6 axes (x, y, z, rx, ry, rz) and the button bitmask.

    Reports only carry what changed in one half (translation or rotation), so
    the state holds the last value of every axis between reports.
    """

    axes: list[int] = field(default_factory=lambda: [0] * 6)
    buttons: int = 0


def apply_report(state: RawState, report: bytes | bytearray | list[int]) -> str | None:
    """Update `state` from one report; returns which part changed.

    Returns "translation", "rotation", "motion" (combined report), "buttons",
    or None for a report this parser ignores (battery, LEDs, too short).
    """
    data = bytes(report)
    if len(data) < 2:
        return None
    report_id = data[0]
    if report_id == 1 and len(data) >= 13:
        state.axes[:] = struct.unpack_from("<6h", data, 1)
        return "motion"
    if report_id == 1 and len(data) >= 7:
        state.axes[0:3] = struct.unpack_from("<3h", data, 1)
        return "translation"
    if report_id == 2 and len(data) >= 7:
        state.axes[3:6] = struct.unpack_from("<3h", data, 1)
        return "rotation"
    if report_id == 3:
        state.buttons = int.from_bytes(data[1:], "little")
        return "buttons"
    return None


def normalize(raw: list[int] | np.ndarray, deadzone: float) -> np.ndarray:
    """Raw counts -> [-1, 1] per axis, with a deadzone that keeps the output continuous.

    `deadzone` is a fraction of full scale: inside it the axis reads 0; outside,
    the remaining travel is rescaled so that full deflection still reads 1.
    """
    v = np.clip(np.asarray(raw, dtype=float) / FULL_SCALE, -1.0, 1.0)
    if deadzone <= 0.0:
        return v
    mag = np.maximum(np.abs(v) - deadzone, 0.0) / (1.0 - deadzone)
    return np.sign(v) * mag


# Operator stance -> matrix taking HID axes (x right, y toward operator, z down)
# to the world frame (x away from the robot's base, y to the robot's left, z up).
# Both are proper rotations, so the same matrix maps the rotation vector.
STANCES: dict[str, np.ndarray] = {
    # Behind the robot, looking where it looks: push away = +x, push right = -y.
    "behind": np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    # Facing the robot: push away (toward the robot) = -x, push right = +y.
    "facing": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
}

STANCE_HELP = {
    "behind": "operator behind the robot, looking where it looks: push the cap away = +x, right = -y, lift = +z",
    "facing": "operator facing the robot: push the cap toward the robot = -x, right = +y, lift = +z",
}


def to_world(axes: np.ndarray, stance: str) -> tuple[np.ndarray, np.ndarray]:
    """Normalized HID axes (6,) -> (translation, rotation) unit vectors in the world frame."""
    m = STANCES[stance]
    return m @ axes[:3], m @ axes[3:6]


def encode_separate(x: int, y: int, z: int, rx: int, ry: int, rz: int) -> tuple[bytes, bytes]:
    """The two reports an older (separate-layout) device sends for one motion."""
    return struct.pack("<B3h", 1, x, y, z), struct.pack("<B3h", 2, rx, ry, rz)


def encode_combined(x: int, y: int, z: int, rx: int, ry: int, rz: int) -> bytes:
    """The 13-byte report a newer (combined-layout) device sends for one motion."""
    return struct.pack("<B6h", 1, x, y, z, rx, ry, rz)


def encode_buttons(mask: int, size: int = 2) -> bytes:
    """A buttons report: id 3 then the bitmask, little-endian, `size` bytes."""
    return bytes([3]) + mask.to_bytes(size, "little")
