"""Load a recorded episode (MCAP or HDF5) into arrays, whatever state the file was left in.

The one public API for reading episodes: `load_episode`, `find_episodes`, the `Episode` it
returns and the metadata types it holds (`EpisodeMeta`, `ArmMeta`, the `control` values
CONTROL_HUMAN / CONTROL_POLICY), so readers (export, learning, generation) need nothing of
recorder/'s file layout, which only this module and replay/convert.py take apart.

Every problem with a file becomes an EpisodeError whose one-line message names
the file and what is wrong, so the CLI can print it as is.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
from mcap.records import Attachment, Channel, Message, Metadata

from recorder import format as schema
from recorder.format import CONTROL_HUMAN, CONTROL_POLICY, ArmMeta, EpisodeMeta
from replay.errors import TeleopError, first_line
from replay.mcap_read import McapScan, iter_records
from scenes.cameras.extra import CameraSpecError, ExtraCamera, model_with_cameras

EPISODE_SUFFIXES = (".mcap", ".hdf5", ".h5")

__all__ = [
    "CONTROL_HUMAN", "CONTROL_POLICY", "EPISODE_SUFFIXES", "ArmMeta", "Episode", "EpisodeError", "EpisodeMeta",
    "find_episodes", "load_episode", "sniff_format",
]


class EpisodeError(TeleopError, ValueError):
    """An episode file is missing, unreadable or inconsistent; the message is one line."""


@dataclass
class Episode:
    """One recorded episode, all steps in memory (T rows)."""

    path: Path
    format: str  # "mcap" | "hdf5"
    meta: EpisodeMeta  # what the file says about itself, with the model XML and assets
    time: np.ndarray  # (T,)
    state: np.ndarray  # (T, nstate) mjSTATE_INTEGRATION before each step
    ctrl: np.ndarray  # (T, nu)
    ee_target: np.ndarray  # (T, n_arms, 7) xyz + quat wxyz
    ee_pose: np.ndarray  # (T, n_arms, 7)
    qpos: np.ndarray  # (T, nq)
    qvel: np.ndarray  # (T, nv)
    gripper: np.ndarray  # (T, n_arms)
    commands: list[list[dict]]
    truncated: bool  # read from a file cut short (no footer / writer never closed it)
    wall_time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truncated_reason: str = ""
    control: np.ndarray | None = None  # (T,) who drove each step (CONTROL_HUMAN/POLICY); None if not recorded

    @property
    def steps(self) -> int:
        return len(self.time)

    @property
    def substeps(self) -> int:
        return self.meta.substeps

    @property
    def seconds(self) -> float:
        """Simulated duration covered by the recorded steps."""
        dt = self.meta.timestep * self.substeps
        return self.steps * dt if dt > 0 else float(self.time[-1] - self.time[0]) if self.steps else 0.0

    def build_model(self, cameras: Sequence[ExtraCamera] = ()) -> mujoco.MjModel:
        """Compile the recorded model XML with its assets, checked against the recorded state size.

        `cameras`: fixed cameras to add to the recorded model (for rendering; nothing the
        physics reads changes). A name the recording already has is an EpisodeError.
        """
        xml = self.meta.model_xml
        if not xml:
            raise EpisodeError(f"{self.path}: no model XML recorded")
        try:
            if cameras:
                model = model_with_cameras(xml, self.meta.assets, cameras)
            else:
                model = mujoco.MjModel.from_xml_string(xml, dict(self.meta.assets))
        except CameraSpecError as exc:
            raise EpisodeError(f"{self.path}: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - mujoco raises ValueError/Exception variants
            first = first_line(exc)
            raise EpisodeError(f"{self.path}: recorded model XML does not compile: {first}") from None
        timestep = self.meta.timestep
        if timestep:
            model.opt.timestep = float(timestep)
        need = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)
        if self.state.shape[1] != need:
            raise EpisodeError(
                f"{self.path}: recorded state vectors have {self.state.shape[1]} values, "
                f"the recorded model needs {need}"
            )
        for name, arr, size in (("ctrl", self.ctrl, model.nu), ("qpos", self.qpos, model.nq), ("qvel", self.qvel, model.nv)):
            if arr.shape[1] != size:
                raise EpisodeError(f"{self.path}: recorded {name} has {arr.shape[1]} values, the model needs {size}")
        return model


def sniff_format(path: Path) -> str:
    """'mcap' or 'hdf5' from the file's magic bytes (suffixes lie)."""
    path = Path(path)
    if not path.exists():
        raise EpisodeError(f"{path}: no such file")
    if path.is_dir():
        raise EpisodeError(f"{path}: is a directory, not an episode file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        raise EpisodeError(f"{path}: cannot read: {exc.strerror}") from None
    if not head:
        raise EpisodeError(f"{path}: file is empty")
    if head == schema.MCAP_MAGIC:
        return "mcap"
    if head == schema.HDF5_MAGIC:
        return "hdf5"
    raise EpisodeError(f"{path}: not an MCAP or HDF5 file")


def load_episode(path: str | Path) -> Episode:
    """Read an episode; a crash-truncated file loads with truncated=True."""
    path = Path(path)
    fmt = sniff_format(path)
    try:
        return _load_mcap(path) if fmt == "mcap" else _load_hdf5(path)
    except EpisodeError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:  # corrupt in a way not checked for above
        first = (str(exc).strip().splitlines() or [""])[0]
        raise EpisodeError(f"{path}: unreadable {fmt.upper()} episode: {type(exc).__name__}: {first}") from None


def find_episodes(paths: Iterable[str | Path]) -> list[Path]:
    """Expand directories into their episode files, preferring .mcap when both exist."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            by_stem: dict[str, Path] = {}
            for f in sorted(p.iterdir()):
                if f.is_file() and f.suffix in EPISODE_SUFFIXES:
                    if f.stem not in by_stem or f.suffix == ".mcap":
                        by_stem[f.stem] = f
            out.extend(by_stem[s] for s in sorted(by_stem))
        elif p.exists():
            out.append(p)
        else:
            raise EpisodeError(f"{p}: no such file or directory")
    return out


# -- MCAP ------------------------------------------------------------------


def _load_mcap(path: Path) -> Episode:
    scan = McapScan()
    start: dict | None = None
    end: dict = {}
    assets: dict[str, bytes] = {}
    model_xml: str | None = None
    channels: dict[int, str] = {}
    step_msgs: list[tuple[int, bytes]] = []
    commands: dict[int, list[dict]] = {}
    for rec in iter_records(path, scan):
        if isinstance(rec, Message):
            topic = channels.get(rec.channel_id)
            if topic == schema.STEP_TOPIC:
                step_msgs.append((rec.sequence, rec.data))
            elif topic == schema.COMMANDS_TOPIC:
                try:
                    body = json.loads(rec.data)
                    commands[int(body["step"])] = list(body["commands"])
                except (ValueError, KeyError, TypeError):
                    raise EpisodeError(f"{path}: bad message on {schema.COMMANDS_TOPIC}") from None
        elif isinstance(rec, Channel):
            channels[rec.id] = rec.topic
        elif isinstance(rec, Metadata):
            if rec.name == schema.META_NAME:
                start = schema.decode_mcap_meta(rec.metadata)
            elif rec.name == schema.META_END_NAME:
                end = schema.decode_mcap_meta(rec.metadata)
        elif isinstance(rec, Attachment):
            if rec.name == schema.MODEL_ATTACHMENT:
                model_xml = rec.data.decode()
            elif rec.name.startswith(schema.ASSET_PREFIX):
                assets[rec.name[len(schema.ASSET_PREFIX) :]] = bytes(rec.data)
    if start is None:
        why = f" (file cut short: {scan.reason})" if scan.truncated else ""
        raise EpisodeError(f"{path}: not a teleop episode: no '{schema.META_NAME}' metadata{why}")
    if model_xml is None:
        raise EpisodeError(f"{path}: no '{schema.MODEL_ATTACHMENT}' attachment")
    meta = _meta(path, lambda: schema.meta_from_mcap(start, end, model_xml, assets))
    layout = meta.layout.fields
    width = meta.layout.width
    step_msgs.sort(key=lambda m: m[0])
    for i, (seq, data) in enumerate(step_msgs):
        if seq != i:
            raise EpisodeError(f"{path}: step {i} is missing from {schema.STEP_TOPIC}")
        if len(data) != width * 8:
            raise EpisodeError(
                f"{path}: step {i} has {len(data) // 8} values, the recorded layout needs {width}"
            )
    raw = b"".join(d for _, d in step_msgs)
    rows = np.frombuffer(raw, dtype="<f8").reshape(len(step_msgs), width)
    cmds = [commands.get(k, []) for k in range(len(rows))]
    return _episode(path, "mcap", meta, rows, layout, cmds, scan.truncated, scan.reason)


def _meta(path: Path, build) -> EpisodeMeta:
    """Build the metadata, naming the file in the one-line error if it is unusable."""
    try:
        return build()
    except KeyError as exc:
        raise EpisodeError(f"{path}: metadata lacks {exc.args[0]}") from None
    except (TypeError, ValueError) as exc:
        raise EpisodeError(f"{path}: {first_line(exc)}") from None


def _episode(path, fmt, meta, rows, layout, cmds, truncated, reason) -> Episode:
    cols = meta.layout.split(np.ascontiguousarray(rows))
    return Episode(
        path=path,
        format=fmt,
        meta=meta,
        time=cols["time"],
        state=np.ascontiguousarray(cols["state"]),
        ctrl=np.ascontiguousarray(cols["ctrl"]),
        ee_target=np.ascontiguousarray(cols["ee_target"]),
        ee_pose=np.ascontiguousarray(cols["ee_pose"]),
        qpos=np.ascontiguousarray(cols["qpos"]),
        qvel=np.ascontiguousarray(cols["qvel"]),
        gripper=np.ascontiguousarray(cols["gripper"]),
        commands=cmds,
        truncated=truncated,
        wall_time=np.ascontiguousarray(cols["wall_time"]),
        truncated_reason=reason,
        control=np.ascontiguousarray(cols["control"]) if "control" in cols else None,
    )


# -- HDF5 ------------------------------------------------------------------

DEMO = schema.HDF5_DEMO


def _load_hdf5(path: Path) -> Episode:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        first = first_line(exc, "unreadable")
        raise EpisodeError(f"{path}: cannot open as HDF5 (truncated or corrupt?): {first}") from None
    with f:
        if DEMO not in f:
            raise EpisodeError(f"{path}: missing group {DEMO}")
        demo = f[DEMO]
        if "teleop_meta" not in demo.attrs:
            raise EpisodeError(f"{path}: not a teleop episode: {DEMO} has no 'teleop_meta' attribute")
        if "model_file" not in demo.attrs:
            raise EpisodeError(f"{path}: {DEMO} has no 'model_file' attribute")
        try:
            teleop_meta = json.loads(demo.attrs["teleop_meta"])
        except ValueError:
            raise EpisodeError(f"{path}: {DEMO} attribute 'teleop_meta' is not JSON") from None
        assets = {}
        if "assets" in demo:
            for ds in demo["assets"].values():
                assets[_text(ds.attrs["name"])] = ds[()].tobytes()
        closed = bool(demo.attrs.get("closed", True))
        # The outcome is the demo attrs (schema 1 files also copied it into teleop_meta at close).
        outcome = {k: (bool(demo.attrs[k]) if k in demo.attrs else None) for k in ("success", "complete")}
        meta = _meta(path, lambda: schema.meta_from_hdf5(
            teleop_meta, _text(demo.attrs["model_file"]), assets, outcome["success"], outcome["complete"], closed, None))
        layout = meta.layout
        sizes = dict(layout.fields)
        datasets = schema.hdf5_datasets(layout)
        names = [d.path for d in datasets] + [schema.HDF5_COMMANDS]
        for name in names:
            if name not in demo:
                raise EpisodeError(f"{path}: missing dataset {DEMO}/{name}")
        lengths = [demo[name].shape[0] for name in names]
        n = min(lengths + [int(demo.attrs.get("num_samples", min(lengths)))])
        if closed:
            meta = meta.with_outcome(meta.success, meta.complete, n)
        try:
            columns = {}
            for d in datasets:
                ds = demo[d.path]
                width = int(np.prod(ds.shape[1:], dtype=np.int64))  # known without rows: 0-step episodes too
                if width != sizes[d.field]:
                    raise EpisodeError(
                        f"{path}: dataset {DEMO}/{d.path} has {width} values per step, "
                        f"the metadata says {sizes[d.field]}"
                    )
                columns[d.field] = np.asarray(ds[:n], dtype=np.float64)
            raw_cmds = demo[schema.HDF5_COMMANDS][:n]
        except OSError as exc:
            raise EpisodeError(f"{path}: cannot read datasets (truncated or corrupt?): {exc}") from None
        cmds = []
        for i, c in enumerate(raw_cmds):
            try:
                cmds.append(json.loads(_text(c)) if len(c) else [])
            except ValueError:
                raise EpisodeError(f"{path}: {DEMO}/{schema.HDF5_COMMANDS}[{i}] is not JSON") from None
    rows = layout.join(columns)
    truncated = not closed
    return _episode(path, "hdf5", meta, rows, layout.fields, cmds, truncated, "" if closed else "writer never closed the file")


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)
