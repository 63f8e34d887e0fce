"""MCAP episode file: the live format, readable in Foxglove and after a crash.

Channels (all messages of one step share log_time = episode start wall clock +
sim time since the first step, so the timeline runs at sim rate):
  /teleop/step        teleop.step.v1 binary rows (see recorder.format)
  /teleop/commands    JSON {"step", "commands"} when a device sent anything
  /tf/armN/ee         foxglove.FrameTransform world -> armN/ee (actual pose)
  /tf/armN/ee_target  foxglove.FrameTransform world -> armN/ee_target
  /joint_states       teleop.JointState JSON {timestamp, name, position, velocity}
Foxglove quaternions are xyzw; the session's are wxyz, so they are reordered here.
"""

from __future__ import annotations

import functools
import json
import math
import time
from pathlib import Path

import mujoco
import numpy as np
from mcap.writer import CompressionType, Writer

from recorder import format as schema
from recorder.format import EpisodeMeta, Outcome

_TIME_SCHEMA = {
    "type": "object",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
}
_XYZ = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_XYZW = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
FRAME_TRANSFORM_JSONSCHEMA = {
    "title": "foxglove.FrameTransform",
    "description": "A transform between two reference frames in 3D space",
    "type": "object",
    "properties": {
        "timestamp": _TIME_SCHEMA,
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _XYZ,
        "rotation": _XYZW,
    },
}
JOINT_STATE_JSONSCHEMA = {
    "title": schema.JOINT_STATE_SCHEMA,
    "description": "Positions (m or rad) and velocities of the model's hinge and slide joints",
    "type": "object",
    "properties": {
        "timestamp": _TIME_SCHEMA,
        "name": {"type": "array", "items": {"type": "string"}},
        "position": {"type": "array", "items": {"type": "number"}},
        "velocity": {"type": "array", "items": {"type": "number"}},
    },
}
COMMANDS_JSONSCHEMA = {
    "title": "teleop.Commands",
    "description": "Device commands received during one control step",
    "type": "object",
    "properties": {"step": {"type": "integer"}, "commands": {"type": "array"}},
}

# A chunk is cut at every periodic flush anyway; this only caps memory.
CHUNK_SIZE = 256 * 1024


@functools.lru_cache(maxsize=8)
def _joint_map(model_xml: str, asset_items: tuple) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names and qpos/qvel indices of the 1-dof joints (arm and fingers).

    Compiled once per model per process; free joints (objects) are left out.
    """
    try:
        model = mujoco.MjModel.from_xml_string(model_xml, dict(asset_items))
    except Exception:  # noqa: BLE001 - the channel is a convenience; fall back to raw qpos
        return [], np.zeros(0, int), np.zeros(0, int)
    names, qi, vi = [], [], []
    for j in range(model.njnt):
        if int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            names.append(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}")
            qi.append(model.jnt_qposadr[j])
            vi.append(model.jnt_dofadr[j])
    return names, np.array(qi, int), np.array(vi, int)


_XYZ_XYZW = [0, 1, 2, 4, 5, 6, 3]  # our x y z qw qx qy qz -> Foxglove's x y z qx qy qz qw


def _tf_template(child: str) -> str:
    """foxglove.FrameTransform JSON with % slots: sec, nsec, x, y, z, qx, qy, qz, qw."""
    head = json.dumps({"parent_frame_id": schema.WORLD_FRAME, "child_frame_id": child})[1:-1]
    return (
        '{"timestamp":{"sec":%d,"nsec":%d},' + head.replace("%", "%%") + ","
        '"translation":{"x":%.9g,"y":%.9g,"z":%.9g},"rotation":{"x":%.9g,"y":%.9g,"z":%.9g,"w":%.9g}}'
    )


def _finite_or_none(values: list[float]) -> list[float | None]:
    return [v if math.isfinite(v) else None for v in values]


def _tf_json(sec: int, nsec: int, template: str, v: list[float]) -> bytes:
    """Slow path for a pose with NaN/inf (not valid JSON numbers): those become null."""
    msg = json.loads(template.replace("%.9g", "0") % (sec, nsec))
    x, y, z, qx, qy, qz, qw = _finite_or_none(v)
    msg["translation"] = {"x": x, "y": y, "z": z}
    msg["rotation"] = {"x": qx, "y": qy, "z": qz, "w": qw}
    return json.dumps(msg).encode()


class McapSink:
    """Writes an episode's rows to an MCAP file, flushed to the OS on demand."""

    format = "mcap"
    # A short sleep every few rows. sleep(0) is not enough: the writer re-takes the GIL
    # before a waiting control thread wakes up, which then waits out Python's 5 ms
    # switch interval. Offline conversion sets this to 0.
    yield_s = 50e-6
    yield_every = 4  # rows

    def __init__(self, path: Path, meta: EpisodeMeta, t0_ns: int | None = None):
        self.path = path
        self._t0_ns = time.time_ns() if t0_ns is None else t0_ns
        self._file = open(path, "xb")  # never overwrite
        try:
            self._setup(meta)
        except BaseException:
            self.abort()
            path.unlink(missing_ok=True)
            raise

    def _setup(self, meta: EpisodeMeta) -> None:
        layout = meta.layout.fields
        self._cols = meta.layout.slices
        self._n_arms = meta.n_arms
        self._sim_t0: float | None = None
        self._count = 0
        w = self._writer = Writer(self._file, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        w.start(profile="", library="teleop-recorder")
        w.add_metadata(schema.META_NAME, schema.encode_mcap_meta(meta.to_json()))
        w.add_attachment(0, 0, schema.MODEL_ATTACHMENT, "application/xml", meta.model_xml.encode())
        for name, data in meta.assets.items():
            w.add_attachment(0, 0, schema.ASSET_PREFIX + name, "application/octet-stream", bytes(data))

        def json_channel(topic: str, schema_name: str, body: dict) -> int:
            sid = w.register_schema(schema_name, "jsonschema", json.dumps(body).encode())
            return w.register_channel(topic, "json", sid)

        step_sid = w.register_schema(schema.STEP_ENCODING, "", b"")
        self._step_ch = w.register_channel(
            schema.STEP_TOPIC,
            schema.STEP_ENCODING,
            step_sid,
            {"layout": json.dumps(layout), "dtype": "<f8"},
        )
        self._cmd_ch = json_channel(schema.COMMANDS_TOPIC, "teleop.Commands", COMMANDS_JSONSCHEMA)
        self._tf_ch = []
        for arm in range(self._n_arms):
            for kind in ("ee", "ee_target"):
                ch = json_channel(f"/tf/arm{arm}/{kind}", schema.FRAME_TRANSFORM_SCHEMA, FRAME_TRANSFORM_JSONSCHEMA)
                self._tf_ch.append((ch, f"arm{arm}/{kind}", "ee_pose" if kind == "ee" else "ee_target", arm))
        self._js_ch = json_channel(schema.JOINT_STATES_TOPIC, schema.JOINT_STATE_SCHEMA, JOINT_STATE_JSONSCHEMA)
        assets = tuple(sorted((k, bytes(v)) for k, v in meta.assets.items()))
        names, qi, vi = _joint_map(meta.model_xml, assets)
        if not names:
            names = [f"qpos{i}" for i in range(meta.nq)]
            qi = vi = None
        self._joint_names, self._qi, self._vi = names, qi, vi
        self._names_json = json.dumps(names)
        self._tf_templates = {frame: _tf_template(frame) for _, frame, _, _ in self._tf_ch}
        self.flush()

    def write(self, rows: np.ndarray, commands: list[str]) -> None:
        """Append rows (n, width); commands[i] is the JSON list of rows[i]'s device commands.

        JSON is built from templates over whole-batch lists (%.9g is plenty for
        viewing; the exact numbers are in the binary step channel): json.dumps
        per message cost more than the rest of the recorder together.
        """
        n = len(rows)
        if not n:
            return
        w, cols = self._writer, self._cols
        if self._sim_t0 is None:
            self._sim_t0 = float(rows[0, 0])
        ns_all = (self._t0_ns + np.round((rows[:, 0] - self._sim_t0) * 1e9).astype(np.int64)).tolist()
        tf_vals = []
        for ch, frame, field, arm in self._tf_ch:
            block = rows[:, cols[field]][:, arm * 7 : arm * 7 + 7][:, _XYZ_XYZW]
            tf_vals.append((ch, self._tf_templates[frame], block.tolist(), bool(np.isfinite(block).all())))
        qpos, qvel = rows[:, cols["qpos"]], rows[:, cols["qvel"]]
        if self._qi is not None:
            pos, vel = qpos[:, self._qi], qvel[:, self._vi]
        else:
            pos, vel = qpos, qvel[:, :0]
        js_finite = bool(np.isfinite(pos).all() and np.isfinite(vel).all())
        pos_l, vel_l = pos.tolist(), vel.tolist()
        pos_fmt, vel_fmt = ",".join(["%.9g"] * pos.shape[1]), ",".join(["%.9g"] * vel.shape[1])
        for i in range(n):
            k = self._count
            self._count += 1
            ns = ns_all[i]
            sec, nsec = divmod(ns, 1_000_000_000)
            w.add_message(self._step_ch, ns, rows[i].tobytes(), ns, k)
            if commands[i] != "[]":
                w.add_message(self._cmd_ch, ns, f'{{"step":{k},"commands":{commands[i]}}}'.encode(), ns, k)
            for ch, template, vals, finite in tf_vals:
                v = vals[i]
                if finite:
                    data = (template % (sec, nsec, *v)).encode()
                else:
                    data = _tf_json(sec, nsec, template, v)
                w.add_message(ch, ns, data, ns, k)
            if js_finite:
                data = (
                    f'{{"timestamp":{{"sec":{sec},"nsec":{nsec}}},"name":{self._names_json},'
                    f'"position":[{pos_fmt % tuple(pos_l[i])}],"velocity":[{vel_fmt % tuple(vel_l[i])}]}}'
                ).encode()
            else:
                data = json.dumps(
                    {"timestamp": {"sec": sec, "nsec": nsec}, "name": self._joint_names,
                     "position": _finite_or_none(pos_l[i]), "velocity": _finite_or_none(vel_l[i])}
                ).encode()
            w.add_message(self._js_ch, ns, data, ns, k)
            if self.yield_s and i % self.yield_every == self.yield_every - 1:
                time.sleep(self.yield_s)  # hand the GIL to the control thread now and then

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (survives kill -9)."""
        self._writer.flush()

    def finish(self, outcome: Outcome) -> None:
        self._writer.flush()  # every message before the end record: a file cut before it reads as incomplete
        self._writer.add_metadata(schema.META_END_NAME, schema.encode_mcap_meta(outcome.to_json()))
        self._writer.finish()
        self._file.close()

    def abort(self) -> None:
        """Close the handle without a footer (after a write error, or before deleting). Never raises.

        After a write error the file ends in a cut chunk; the linear reader
        (replay.mcap_read) keeps every whole chunk before it.
        """
        if not self._file.closed:
            try:
                self._file.close()  # may retry writing what the OS refused: that fails again, and the handle closes anyway
            except OSError:
                pass
