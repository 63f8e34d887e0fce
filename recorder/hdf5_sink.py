"""HDF5 episode file in robomimic's layout, grown in place and flushed as it goes.

robomimic reads data/demo_N/{actions, states, obs/*, rewards, dones} with attrs
`model_file` and `num_samples`, and data attrs `env_args` (JSON) and `total`.
Here `states` is the full mjSTATE_INTEGRATION vector (not robosuite's
[time, qpos, qvel], which cannot replay exactly) and `actions` is ctrl. The extra
datasets (ctrl, time, wall_time, ee_target, ee_pose, gripper, commands) and the
`teleop_meta` JSON attr carry what exact replay and inspection need.
Rows are written every WRITE_PERIOD seconds (ALONGSIDE_MCAP_PERIOD when an MCAP
file records the same episode: that one is the live format with the tight loss
bound, and each HDF5 write holds the GIL for about a millisecond), then
`num_samples`/`total` are updated and the file flushed, so a file whose writer
died still says how many rows are whole.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import h5py
import numpy as np

from replay import schema

DEMO = "data/demo_0"
_CHUNK_ROWS = 256
WRITE_PERIOD = 0.5  # s between HDF5 writes; a crash loses at most about this much
ALONGSIDE_MCAP_PERIOD = 2.0  # s between writes when MCAP records the episode too


class Hdf5Sink:
    """Writes an episode's rows to a robomimic-style HDF5 file."""

    format = "hdf5"

    def __init__(self, path: Path, meta: dict, layout: list[tuple[str, int]], write_period: float = WRITE_PERIOD):
        self.path = path
        self.write_period = write_period
        self._cols = schema.slices(layout)
        self._n_arms = schema.n_arms_of(meta)
        self._n = 0
        self._pending: list[tuple[np.ndarray, list[str]]] = []
        self._last_write = 0.0
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
        # dataset path -> (row field, trailing shape). Duplicates robomimic wants
        # under another name are soft links, written once.
        self._spec: dict[str, tuple[str, tuple[int, ...]]] = {
            "states": ("state", (width["state"],)),
            "actions": ("ctrl", (width["ctrl"],)),
            "time": ("time", ()),
            "wall_time": ("wall_time", ()),
            "ee_target": ("ee_target", (na, 7)),
            "ee_pose": ("ee_pose", (na, 7)),
            "obs/qpos": ("qpos", (width["qpos"],)),
            "obs/qvel": ("qvel", (width["qvel"],)),
            "obs/gripper": ("gripper", (na,)),
        }
        self._ds = {}
        for name, (_, shape) in self._spec.items():
            self._ds[name] = demo.create_dataset(
                name, shape=(0, *shape), maxshape=(None, *shape), dtype="<f8", chunks=(_CHUNK_ROWS, *shape)
            )
        demo["ctrl"] = h5py.SoftLink(f"/{DEMO}/actions")
        demo["gripper"] = h5py.SoftLink(f"/{DEMO}/obs/gripper")
        self._cmds = demo.create_dataset(
            "commands", shape=(0,), maxshape=(None,), dtype=h5py.string_dtype(), chunks=(_CHUNK_ROWS,)
        )
        self._demo, self._data = demo, data
        f.flush()

    def write(self, rows: np.ndarray, commands: list[str]) -> None:
        """Queue rows; they reach the file at the next flush that is due."""
        if len(rows):
            self._pending.append((rows, commands))

    def flush(self, force: bool = False) -> None:
        """Write queued rows, publish the row count, push HDF5's buffers to the OS.

        Each write costs ~1 ms whatever its size, so it happens at most every
        `write_period` seconds unless forced.
        """
        if not self._pending or (not force and time.monotonic() - self._last_write < self.write_period):
            return
        rows = np.concatenate([r for r, _ in self._pending])
        commands = [c for _, cs in self._pending for c in cs]
        self._pending.clear()
        n0, n = self._n, len(rows)
        for name, (field, shape) in self._spec.items():
            ds = self._ds[name]
            ds.resize(n0 + n, axis=0)
            ds[n0 : n0 + n] = rows[:, self._cols[field]].reshape(n, *shape)
        self._cmds.resize(n0 + n, axis=0)
        self._cmds[n0 : n0 + n] = commands
        self._n = n0 + n
        self._demo.attrs["num_samples"] = self._n
        self._data.attrs["total"] = self._n
        self._f.flush()
        self._last_write = time.monotonic()

    def finish(self, end_meta: dict) -> None:
        self.flush(force=True)
        demo = self._demo
        success, complete = bool(end_meta["success"]), bool(end_meta["complete"])
        # robomimic's per-step reward/done: only the last step is known to end the demo.
        dones = np.zeros(self._n, dtype=np.int64)
        rewards = np.zeros(self._n)
        if self._n:
            dones[-1] = 1
            rewards[-1] = 1.0 if success else 0.0
        demo.create_dataset("dones", data=dones)
        demo.create_dataset("rewards", data=rewards)
        # Flat (T, n_arms*7) EE poses as robomimic low-dim observations.
        for name in ("ee_pose", "ee_target"):
            demo.create_dataset(f"obs/{name}", data=self._ds[name][: self._n].reshape(self._n, self._n_arms * 7))
        meta = json.loads(demo.attrs["teleop_meta"])
        meta.update(end_meta)
        demo.attrs["teleop_meta"] = json.dumps(meta)
        demo.attrs["success"] = success
        demo.attrs["complete"] = complete
        demo.attrs["closed"] = True
        self._f.close()

    def abort(self) -> None:
        try:
            self._f.close()
        except Exception:  # noqa: BLE001 - closing before delete; nothing to save
            pass
