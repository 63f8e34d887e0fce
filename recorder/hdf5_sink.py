"""HDF5 episode file in robomimic's layout, grown in place and flushed as it goes.

robomimic reads data/demo_N/{actions, states, obs/*, rewards, dones} with attrs
`model_file` and `num_samples`, and data attrs `env_args` (JSON) and `total`.
Here `states` is the full mjSTATE_INTEGRATION vector (not robosuite's
[time, qpos, qvel], which cannot replay exactly) and `actions` is ctrl. The extra
datasets (ctrl, time, wall_time, ee_target, ee_pose, gripper, commands) and the
`teleop_meta` JSON attr carry what exact replay and inspection need.
`num_samples`/`total` are updated at every flush, so a file whose writer died
still says how many rows are whole.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from replay import schema

DEMO = "data/demo_0"
_CHUNK_ROWS = 256


class Hdf5Sink:
    """Writes an episode's rows to a robomimic-style HDF5 file."""

    format = "hdf5"

    def __init__(self, path: Path, meta: dict, layout: list[tuple[str, int]]):
        self.path = path
        self._cols = schema.slices(layout)
        self._n_arms = schema.n_arms_of(meta)
        self._n = 0
        # v108: dense attribute storage, so a large model XML fits in `model_file`.
        self._f = f = h5py.File(path, "w-", libver=("v108", "latest"))
        try:
            self._setup(meta)
        except BaseException:
            f.close()
            path.unlink(missing_ok=True)
            raise

    def _setup(self, meta: dict) -> None:
        f = self._f
        data = f.create_group("data")
        env_meta = {k: v for k, v in meta.items() if k not in schema.BINARY_META_KEYS}
        data.attrs["env_args"] = json.dumps(
            {"env_name": meta.get("scene", ""), "type": 0, "env_kwargs": env_meta, "source": "teleop"}
        )
        data.attrs["total"] = 0
        data.attrs["date"] = str(meta.get("start_time", ""))
        demo = f.create_group(DEMO)
        demo.attrs["model_file"] = meta["model_xml"]
        demo.attrs["num_samples"] = 0
        demo.attrs["teleop_meta"] = json.dumps(env_meta)
        for key in ("scene", "robot", "seed", "task", "mujoco_version", "schema_version"):
            if key in meta and meta[key] is not None:
                demo.attrs[key] = meta[key]
        demo.attrs["success"] = False
        demo.attrs["complete"] = False
        demo.attrs["closed"] = False  # True only once close() finished the file
        assets = demo.create_group("assets")
        for i, (name, blob) in enumerate((meta.get("assets") or {}).items()):
            ds = assets.create_dataset(f"{i:04d}", data=np.frombuffer(bytes(blob), dtype=np.uint8))
            ds.attrs["name"] = name
        c = self._cols
        width = {k: s.stop - s.start for k, s in c.items()}
        na = self._n_arms
        # dataset path -> (row field, trailing shape)
        self._spec: dict[str, tuple[str, tuple[int, ...]]] = {
            "states": ("state", (width["state"],)),
            "actions": ("ctrl", (width["ctrl"],)),
            "ctrl": ("ctrl", (width["ctrl"],)),
            "time": ("time", ()),
            "wall_time": ("wall_time", ()),
            "ee_target": ("ee_target", (na, 7)),
            "ee_pose": ("ee_pose", (na, 7)),
            "gripper": ("gripper", (na,)),
            "obs/qpos": ("qpos", (width["qpos"],)),
            "obs/qvel": ("qvel", (width["qvel"],)),
            "obs/ee_pose": ("ee_pose", (na * 7,)),
            "obs/ee_target": ("ee_target", (na * 7,)),
            "obs/gripper": ("gripper", (na,)),
        }
        self._ds = {}
        for name, (_, shape) in self._spec.items():
            self._ds[name] = demo.create_dataset(
                name, shape=(0, *shape), maxshape=(None, *shape), dtype="<f8", chunks=(_CHUNK_ROWS, *shape)
            )
        self._cmds = demo.create_dataset(
            "commands", shape=(0,), maxshape=(None,), dtype=h5py.string_dtype(), chunks=(_CHUNK_ROWS,)
        )
        self._rewards = demo.create_dataset("rewards", shape=(0,), maxshape=(None,), dtype="<f8", chunks=(_CHUNK_ROWS,))
        self._dones = demo.create_dataset("dones", shape=(0,), maxshape=(None,), dtype="<i8", chunks=(_CHUNK_ROWS,))
        self._demo, self._data = demo, data
        f.flush()

    def write(self, rows: np.ndarray, commands: list[list[dict]]) -> None:
        n0, n = self._n, len(rows)
        if not n:
            return
        for name, (field, shape) in self._spec.items():
            ds = self._ds[name]
            ds.resize(n0 + n, axis=0)
            ds[n0 : n0 + n] = rows[:, self._cols[field]].reshape(n, *shape)
        self._cmds.resize(n0 + n, axis=0)
        self._cmds[n0 : n0 + n] = [json.dumps(c) for c in commands]
        for ds in (self._rewards, self._dones):
            ds.resize(n0 + n, axis=0)
            ds[n0 : n0 + n] = 0
        self._n = n0 + n

    def flush(self) -> None:
        """Publish the row count and push HDF5's buffers to the OS."""
        self._demo.attrs["num_samples"] = self._n
        self._data.attrs["total"] = self._n
        self._f.flush()

    def finish(self, end_meta: dict) -> None:
        demo = self._demo
        success, complete = bool(end_meta["success"]), bool(end_meta["complete"])
        if self._n:
            self._dones[self._n - 1] = 1
            self._rewards[self._n - 1] = 1.0 if success else 0.0
        meta = json.loads(demo.attrs["teleop_meta"])
        meta.update(end_meta)
        demo.attrs["teleop_meta"] = json.dumps(meta)
        demo.attrs["success"] = success
        demo.attrs["complete"] = complete
        demo.attrs["closed"] = True
        self.flush()
        self._f.close()

    def abort(self) -> None:
        try:
            self._f.close()
        except Exception:  # noqa: BLE001 - closing before delete; nothing to save
            pass
