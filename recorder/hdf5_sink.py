"""HDF5 episode file in robomimic's layout, grown in place and flushed as it goes.

robomimic reads data/demo_N/{actions, states, obs/*, rewards, dones} with attrs
`model_file` and `num_samples`, and data attrs `env_args` (JSON) and `total`.
Here `states` is the full mjSTATE_INTEGRATION vector (not robosuite's
[time, qpos, qvel], which cannot replay exactly) and `actions` is ctrl. The extra
datasets (ctrl, time, wall_time, ee_target, ee_pose, gripper, commands) and the
`teleop_meta` JSON attr carry what exact replay and inspection need.
Each fact is stored once: `env_args` describes the environment only (EpisodeMeta.env_json);
`teleop_meta` every other metadata key except the outcome; the outcome is the
demo attrs `success`, `complete` (False until finish() writes the final values,
and `closed` says it did) and `num_samples`. At finish the robomimic
observation pairs are added: obs/ee_pose, obs/ee_target and next_obs/<key> for
every obs key (timing in recorder.robomimic_obs), with attr `next_obs_final`.
Rows are written every WRITE_PERIOD seconds (ALONGSIDE_MCAP_PERIOD when an MCAP
file records the same episode: that one is the live format with the tight loss
bound, and each HDF5 write holds the GIL for about a millisecond), then
`num_samples`/`total` are updated and the file flushed, so a file whose writer
died still says how many rows are whole. A write that fails (a full disk) is
undone back to the last flush (recorder.rollback_file): the cut file stays
readable, its `num_samples` honest, and the process does not crash.
"""

from __future__ import annotations

import atexit
import json
import time
import weakref
from dataclasses import fields
from pathlib import Path

import h5py
import numpy as np

from recorder.robomimic_obs import Recorded, obs_pairs
from recorder.rollback_file import RollbackFile
from recorder import format as schema
from recorder.format import EpisodeMeta, Outcome

DEMO = schema.HDF5_DEMO
_CHUNK_ROWS = 256
WRITE_PERIOD = 0.5  # s between HDF5 writes; a crash loses at most about this much
ALONGSIDE_MCAP_PERIOD = 2.0  # s between writes when MCAP records the episode too
ENV_TYPE = 0  # not one of robomimic's EnvType values: robomimic cannot rebuild this environment itself
OUTCOME_KEYS = tuple(f.name for f in fields(Outcome))  # kept out of teleop_meta: demo attrs success, complete, num_samples
_open_sinks: "weakref.WeakSet[Hdf5Sink]" = weakref.WeakSet()


class Hdf5Sink:
    """Writes an episode's rows to a robomimic-style HDF5 file."""

    format = "hdf5"

    def __init__(self, path: Path, meta: EpisodeMeta, write_period: float = WRITE_PERIOD):
        self.path = path
        self.write_period = write_period
        self._cols = meta.layout.slices
        self._n_arms = meta.n_arms
        self._n = 0
        self._pending: list[tuple[np.ndarray, list[str]]] = []
        self._last_write = 0.0
        # HDF5 writes through a RollbackFile: a failed write (full disk) can neither corrupt
        # the file nor crash HDF5 (see recorder.rollback_file). "w-": never overwrite.
        self._file = RollbackFile(path)
        self._f = None
        try:
            # v108: dense attribute storage, so a large model XML fits in `model_file`.
            self._f = h5py.File(self._file, "w", libver=("v108", "latest"))
            self._setup(meta)
            self._settle()
        except BaseException:
            self._close_file()
            path.unlink(missing_ok=True)
            raise
        _open_sinks.add(self)

    def _setup(self, meta: EpisodeMeta) -> None:
        f = self._f
        data = f.create_group("data")
        # Each fact is written once: the environment in env_args, provenance in
        # teleop_meta, the outcome (success, complete, num_samples) as demo attrs
        # that finish() sets to their final values.
        data.attrs["env_args"] = json.dumps({"env_name": meta.scene, "type": ENV_TYPE, "env_kwargs": meta.env_json()})
        data.attrs["total"] = 0
        data.attrs["date"] = meta.start_time
        demo = f.create_group(DEMO)
        demo.attrs["model_file"] = meta.model_xml
        demo.attrs["num_samples"] = 0
        demo.attrs["teleop_meta"] = json.dumps({k: v for k, v in meta.to_json().items() if k not in OUTCOME_KEYS})
        self._sim = {  # what finish() needs to build robomimic's next_obs (robomimic_obs.Recorded)
            "model_xml": meta.model_xml,
            "assets": dict(meta.assets),
            "timestep": meta.timestep,
            "substeps": meta.substeps,
            "ee_sites": [arm.ee_site for arm in meta.arms],
        }
        for key, value in (("scene", meta.scene), ("robot", meta.robot), ("seed", meta.seed), ("task", meta.task),
                           ("mujoco_version", meta.mujoco_version), ("schema_version", meta.schema_version)):
            demo.attrs[key] = value
        demo.attrs["success"] = False
        demo.attrs["complete"] = False
        demo.attrs["closed"] = False  # True only once close() finished the file
        assets = demo.create_group("assets")
        for i, (name, blob) in enumerate(meta.assets.items()):
            ds = assets.create_dataset(f"{i:04d}", data=np.frombuffer(bytes(blob), dtype=np.uint8))
            ds.attrs["name"] = name
        layout = meta.layout
        # dataset path -> (row field, trailing shape), from the one map in recorder.format.
        # Duplicates robomimic wants under another name are soft links, written once.
        self._spec: dict[str, tuple[str, tuple[int, ...]]] = {
            d.path: (d.field, schema.hdf5_shape(d, layout)) for d in schema.hdf5_datasets(layout)
        }
        self._ds = {}
        for name, (_, shape) in self._spec.items():
            self._ds[name] = demo.create_dataset(
                name, shape=(0, *shape), maxshape=(None, *shape), dtype="<f8", chunks=(_CHUNK_ROWS, *shape)
            )
        for link, target in schema.HDF5_LINKS.items():
            demo[link] = h5py.SoftLink(f"/{DEMO}/{target}")
        self._cmds = demo.create_dataset(
            schema.HDF5_COMMANDS, shape=(0,), maxshape=(None,), dtype=h5py.string_dtype(), chunks=(_CHUNK_ROWS,)
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
        if self._file.error is not None:
            raise self._write_error()
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
        self._demo.attrs["num_samples"] = n0 + n
        self._data.attrs["total"] = n0 + n
        self._f.flush()
        self._settle()  # on a write error the file goes back to its last n0 rows, and this raises
        self._n = n0 + n
        self._last_write = time.monotonic()

    def finish(self, outcome: Outcome) -> None:
        self.flush(force=True)
        demo = self._demo
        success, complete = outcome.success, outcome.complete
        # robomimic's per-step reward/done: only the last step is known to end the demo.
        dones = np.zeros(self._n, dtype=np.int64)
        rewards = np.zeros(self._n)
        if self._n:
            dones[-1] = 1
            rewards[-1] = 1.0 if success else 0.0
        demo.create_dataset("dones", data=dones)
        demo.create_dataset("rewards", data=rewards)
        self._write_obs_pairs()
        # The outcome lives in the demo attrs only.
        demo.attrs["success"] = success
        demo.attrs["complete"] = complete
        demo.attrs["closed"] = True
        self._close_file()
        if self._file.error is not None:  # the file went back to its last flushed rows
            raise self._write_error()

    def _write_obs_pairs(self) -> None:
        """obs/ee_pose, obs/ee_target and next_obs/<key> for every obs key (see recorder.robomimic_obs)."""
        n, ds, demo = self._n, self._ds, self._demo
        flat = {name: ds[name][:n].reshape(n, self._n_arms * 7) for name in ("ee_pose", "ee_target")}
        last_two = sorted({max(n - 2, 0), n - 1}) if n else []  # h5py wants increasing, distinct rows
        pairs = obs_pairs(Recorded(
            **self._sim,
            qpos=ds["obs/qpos"][:n], qvel=ds["obs/qvel"][:n], gripper=ds["obs/gripper"][:n],
            ee_pose=flat["ee_pose"], ee_target=flat["ee_target"],
            states=ds["states"][sorted({0, *last_two})] if n else ds["states"][:0],
            actions=ds["actions"][last_two] if n else ds["actions"][:0],
        ))
        for name in ("ee_pose", "ee_target"):
            demo.create_dataset(f"obs/{name}", data=pairs.obs[name])
        for name, value in pairs.next_obs.items():
            demo.create_dataset(f"next_obs/{name}", data=value)
        demo.attrs["next_obs_final"] = pairs.final

    def abort(self) -> None:
        """Close without finishing (after a write error, or before deleting): the file keeps its last flushed rows."""
        self._close_file()

    def _settle(self) -> None:
        """After HDF5 flushed: keep the bytes as the state to come back to, or raise the write error."""
        if self._file.error is not None:
            raise self._write_error()
        self._file.commit()

    def _write_error(self) -> OSError:
        exc = self._file.error
        return OSError(exc.errno, exc.strerror or str(exc), str(self.path))

    def _close_file(self) -> None:
        """Close the HDF5 file once, then undo a failed write and close the OS file. Never raises.

        h5py's close closes every dataset and group of the file with it, so no h5py
        object is left to be finalized later, in whatever order, by the interpreter.
        """
        _open_sinks.discard(self)
        f, self._f = self._f, None
        if f is not None:
            try:
                f.close()
            except Exception:  # noqa: BLE001 - HDF5 never saw a write fail; nothing else is expected here
                pass
        self._file.rollback()
        self._file.close()


@atexit.register
def _close_open_sinks() -> None:
    """Close a file still open at interpreter exit while Python still runs (HDF5's own exit
    hook would call its RollbackFile after the interpreter is gone, and crash)."""
    for sink in list(_open_sinks):
        sink.abort()
