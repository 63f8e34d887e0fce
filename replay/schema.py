"""The on-disk episode schema, shared by the writer (recorder) and the readers (replay).

It lives here, downstream of `recorder`, so that both sides import one definition
and a reader never has to import the writer.

Step row ("teleop.step.v1")
---------------------------
Every control step is one row of little-endian float64 values, concatenated in
the order of `step_layout(...)`:

    time (1) | wall_time (1) | state (nstate) | ctrl (nu) | ee_target (n_arms*7)
    | ee_pose (n_arms*7) | qpos (nq) | qvel (nv) | gripper (n_arms)

ee_target / ee_pose are per arm: x, y, z, qw, qx, qy, qz (MuJoCo's wxyz order).
In MCAP one row is the payload of one message on STEP_TOPIC (message encoding
STEP_ENCODING, its `sequence` is the step index); the layout is repeated in that
channel's metadata and in the episode metadata (`step_layout`), so a reader
never guesses.

Metadata
--------
MCAP: a metadata record named META_NAME holds every metadata key with a
JSON-encoded value, written when the episode starts; a second record named
META_END_NAME (success, complete, steps) is written at close. A file without the
end record was cut short: it reads as success=false, complete=false. The model
XML is the attachment MODEL_ATTACHMENT; each asset is an attachment named
ASSET_PREFIX + its name.

HDF5 (robomimic layout): data/demo_0/{states, actions, obs/*} plus ctrl, time,
wall_time, ee_target, ee_pose, gripper, commands (JSON strings); metadata is the
JSON attr `teleop_meta` of data/demo_0 (without model XML and assets), the XML is
attr `model_file`, assets are uint8 datasets under data/demo_0/assets with attr
`name`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import numpy as np

SCHEMA_VERSION = 1
STEP_ENCODING = "teleop.step.v1"
STEP_TOPIC = "/teleop/step"
COMMANDS_TOPIC = "/teleop/commands"
JOINT_STATES_TOPIC = "/joint_states"
JOINT_STATE_SCHEMA = "teleop.JointState"
FRAME_TRANSFORM_SCHEMA = "foxglove.FrameTransform"
META_NAME = "teleop.episode"
META_END_NAME = "teleop.episode.end"
MODEL_ATTACHMENT = "model.xml"
ASSET_PREFIX = "assets/"
WORLD_FRAME = "world"

MCAP_MAGIC = b"\x89MCAP0\r\n"
HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"

# Keys of the metadata that are not plain JSON (kept out of the JSON blobs).
BINARY_META_KEYS = ("model_xml", "assets")
FIELDS = ("time", "wall_time", "state", "ctrl", "ee_target", "ee_pose", "qpos", "qvel", "gripper")


def step_layout(nstate: int, nu: int, n_arms: int, nq: int, nv: int) -> list[tuple[str, int]]:
    """(field, number of float64 values) in row order."""
    return [
        ("time", 1),
        ("wall_time", 1),
        ("state", nstate),
        ("ctrl", nu),
        ("ee_target", n_arms * 7),
        ("ee_pose", n_arms * 7),
        ("qpos", nq),
        ("qvel", nv),
        ("gripper", n_arms),
    ]


def layout_from_meta(meta: Mapping) -> list[tuple[str, int]]:
    """The row layout an episode's metadata describes."""
    return step_layout(
        int(meta["nstate"]), int(meta["nu"]), n_arms_of(meta), int(meta["nq"]), int(meta["nv"])
    )


def n_arms_of(meta: Mapping) -> int:
    """Number of arms: from the robot spec, else from an explicit n_arms key."""
    if "n_arms" in meta:
        return int(meta["n_arms"])
    spec = meta.get("robot_spec") or {}
    return len(spec.get("arms", [])) or 1


def slices(layout: list[tuple[str, int]]) -> dict[str, slice]:
    """Column slice of each field within a row."""
    out: dict[str, slice] = {}
    start = 0
    for name, size in layout:
        out[name] = slice(start, start + size)
        start += size
    return out


def row_width(layout: list[tuple[str, int]]) -> int:
    return sum(size for _, size in layout)


def encode_meta(meta: Mapping) -> dict[str, str]:
    """MCAP metadata form: every JSON-able key, value JSON-encoded (types survive)."""
    return {k: json.dumps(v) for k, v in meta.items() if k not in BINARY_META_KEYS}


def decode_meta(record: Mapping[str, str]) -> dict:
    out = {}
    for key, value in record.items():
        try:
            out[key] = json.loads(value)
        except (TypeError, ValueError):
            out[key] = value
    return out


def split_rows(rows: np.ndarray, layout: list[tuple[str, int]], n_arms: int) -> dict[str, np.ndarray]:
    """Split (T, width) rows into named (T, ...) arrays (views, no copy)."""
    cols = slices(layout)
    out = {name: rows[:, cols[name]] for name in FIELDS}
    out["time"] = out["time"][:, 0]
    out["wall_time"] = out["wall_time"][:, 0]
    out["ee_target"] = out["ee_target"].reshape(len(rows), n_arms, 7)
    out["ee_pose"] = out["ee_pose"].reshape(len(rows), n_arms, 7)
    return out
