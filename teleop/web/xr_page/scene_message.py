"""What the XR page draws, as the server sends it: the scene once, then every control tick the bodies' poses.

The page draws with its own WebGL2 renderer (xr.js), so only geometry and poses travel; the headset
turns its head at its own frame rate without waiting for the server.

scene (binary, once per model): b"TXR1", uint32 header length, the JSON header (UTF-8, padded with
spaces to 4 bytes), then the meshes' arrays it points at (byte offsets from the start of that data):
float32 vertices (x, y, z, m, in the mesh's own frame) and uint32 triangles. The header holds the
geoms the session page shows (groups 0-2, alpha > 0): type (box, sphere, capsule, cylinder,
ellipsoid, plane, mesh), MuJoCo's size (m), rgba, the body it rides on and its pose in that body
(pos m, quat wxyz); and `placement`: where the operator stands (see `placement`).

poses (binary, every tick): b"TXP1", uint32 tick, uint32 body count N, uint32 arm count A, float64 sim
time (s), float64 the `frame` number of the newest XR pose the tick applied (-1: none), then float32
[N x 7]: each body's world position (m) and quaternion (wxyz), then float32 [A]: each arm's finger
contact normal force (N, the haptics' input), then float32 [A]: each arm's IK tracking error (m: the
target out of reach, a pulse marks it).

All numbers little-endian; the world frame is MuJoCo's (z up, m).
"""

from __future__ import annotations

import json
import math
import struct

import mujoco
import numpy as np

SCENE_MAGIC = b"TXR1"
POSES_MAGIC = b"TXP1"
POSES_HEAD = struct.Struct("<4sIIIdd")
HEADSET_ABOVE_TABLE_M = 0.45  # the table top is this far below the headset at Enter VR / recentre
PLANE_HALF_M = 3.0  # an infinite plane (size 0) is drawn this far from its centre
SHOWN_GROUPS = (0, 1, 2)  # geom groups the session page shows (3 and up: collision parts)
DEFAULT_RGBA = (0.5, 0.5, 0.5, 1.0)  # MuJoCo's default geom rgba: a material's colour wins over it
GEOM_TYPES = {
    mujoco.mjtGeom.mjGEOM_PLANE: "plane", mujoco.mjtGeom.mjGEOM_SPHERE: "sphere",
    mujoco.mjtGeom.mjGEOM_CAPSULE: "capsule", mujoco.mjtGeom.mjGEOM_ELLIPSOID: "ellipsoid",
    mujoco.mjtGeom.mjGEOM_CYLINDER: "cylinder", mujoco.mjtGeom.mjGEOM_BOX: "box", mujoco.mjtGeom.mjGEOM_MESH: "mesh",
}


def _floats(values) -> list[float]:
    return [round(float(v), 6) for v in values]


def placement(model: mujoco.MjModel, bases: list[tuple[np.ndarray, np.ndarray]]) -> dict:
    """Where the operator stands and faces, in the world frame: `stand` (m, at the table top's height) and
    `yaw` (rad about +z of the direction they face), and the headset's height above that point.

    One arm: at its base, facing the base's +x (away from it). Two arms (they face each other across
    the table): at the middle of the table's long side, facing the table, arm 0 on the left and
    arm 1 on the right."""
    table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    if table >= 0:
        top = float(model.geom_pos[table][2] + model.geom_size[table][2])
        centre = np.array(model.geom_pos[table][:2], dtype=float)
        half = np.array(model.geom_size[table][:2], dtype=float)
    else:
        top, centre, half = 0.0, np.zeros(2), np.zeros(2)
    if len(bases) >= 2:
        left, right = np.asarray(bases[0][0][:2], dtype=float), np.asarray(bases[1][0][:2], dtype=float)
        across = right - left
        across /= max(float(np.linalg.norm(across)), 1e-9)
        facing = np.array([-across[1], across[0]])  # z x across: arm 0 on the left
        middle = (left + right) / 2.0
        # back from the middle to the table's edge on the operator's side (the long side: across the arms' line)
        depth = float(abs(facing[0]) * half[0] + abs(facing[1]) * half[1]) if table >= 0 else 0.3
        stand = middle - facing * depth
    else:
        pos, quat = bases[0] if bases else (np.zeros(3), np.array([1.0, 0, 0, 0]))
        forward = np.empty(3)
        mujoco.mju_rotVecQuat(forward, np.array([1.0, 0.0, 0.0]), np.asarray(quat, dtype=float))
        facing = forward[:2] / max(float(np.linalg.norm(forward[:2])), 1e-9)
        stand = np.asarray(pos[:2], dtype=float)
    return {"stand": _floats([stand[0], stand[1], top]), "yaw": round(math.atan2(facing[1], facing[0]), 6),
            "headset_above_m": HEADSET_ABOVE_TABLE_M, "table_centre": _floats(centre), "table_half": _floats(half)}


def _rgba(model: mujoco.MjModel, g: int) -> list[float]:
    rgba = model.geom_rgba[g]
    mat = int(model.geom_matid[g])
    if mat >= 0 and tuple(np.round(rgba, 4)) == DEFAULT_RGBA:
        rgba = model.mat_rgba[mat]
    return _floats(rgba)


def scene_message(model: mujoco.MjModel, bases: list[tuple[np.ndarray, np.ndarray]], arms: int) -> bytes:
    """The scene message (module docstring) of `model`; `bases`: each arm's base (pos, wxyz) for `placement`."""
    geoms, meshes, blobs = [], {}, []
    offset = 0
    for g in range(model.ngeom):
        kind = GEOM_TYPES.get(int(model.geom_type[g]))
        rgba = _rgba(model, g)
        if kind is None or int(model.geom_group[g]) not in SHOWN_GROUPS or rgba[3] <= 0.0:
            continue
        entry = {"body": int(model.geom_bodyid[g]), "type": kind, "size": _floats(model.geom_size[g]), "rgba": rgba,
                 "pos": _floats(model.geom_pos[g]), "quat": _floats(model.geom_quat[g])}
        if kind == "mesh":
            mesh = int(model.geom_dataid[g])
            if mesh not in meshes:
                v0, nv = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
                f0, nf = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
                verts = np.ascontiguousarray(model.mesh_vert[v0:v0 + nv], dtype="<f4").tobytes()
                faces = np.ascontiguousarray(model.mesh_face[f0:f0 + nf], dtype="<u4").tobytes()
                meshes[mesh] = {"vert": offset, "nvert": nv, "face": offset + len(verts), "nface": nf}
                blobs += [verts, faces]
                offset += len(verts) + len(faces)
            entry["mesh"] = mesh
        geoms.append(entry)
    header = {"bodies": int(model.nbody), "arms": int(arms), "geoms": geoms,
              "meshes": {str(k): v for k, v in meshes.items()}, "placement": placement(model, bases)}
    text = json.dumps(header, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    return SCENE_MAGIC + struct.pack("<I", len(text)) + text + b"".join(blobs)


def read_scene_header(message: bytes) -> dict:
    """The JSON header of a scene message (what the page reads first)."""
    if message[:4] != SCENE_MAGIC:
        raise ValueError("not a scene message")
    (length,) = struct.unpack_from("<I", message, 4)
    return json.loads(message[8:8 + length])


def poses_message(tick: int, sim_time: float, xpos: np.ndarray, xquat: np.ndarray, applied_frame: float,
                  forces: np.ndarray, errors: np.ndarray | None = None) -> bytes:
    """The poses message (module docstring): every body's world pose this tick, each arm's finger force and IK error."""
    body = np.concatenate([np.asarray(xpos, dtype="<f4"), np.asarray(xquat, dtype="<f4")], axis=1)
    forces = np.asarray(forces, dtype="<f4").ravel()
    errors = np.zeros(forces.size, dtype="<f4") if errors is None else np.asarray(errors, dtype="<f4").ravel()
    head = POSES_HEAD.pack(POSES_MAGIC, tick & 0xFFFFFFFF, body.shape[0], forces.size, float(sim_time), float(applied_frame))
    return head + body.tobytes() + forces.tobytes() + errors.tobytes()


def read_poses(message: bytes) -> tuple[int, float, float, np.ndarray, np.ndarray]:
    """(tick, sim time, applied frame, poses [N x 7], forces [A]) of a poses message (`read_errors`: the IK errors)."""
    magic, tick, n, arms, sim_time, frame = POSES_HEAD.unpack_from(message, 0)
    if magic != POSES_MAGIC:
        raise ValueError("not a poses message")
    at = POSES_HEAD.size
    poses = np.frombuffer(message, dtype="<f4", count=n * 7, offset=at).reshape(n, 7)
    forces = np.frombuffer(message, dtype="<f4", count=arms, offset=at + n * 28)
    return tick, sim_time, frame, poses, forces


def read_errors(message: bytes) -> np.ndarray:
    """Each arm's IK tracking error (m) in a poses message."""
    _, _, n, arms, _, _ = POSES_HEAD.unpack_from(message, 0)
    return np.frombuffer(message, dtype="<f4", count=arms, offset=POSES_HEAD.size + n * 28 + arms * 4)
