"""The episode format, defined once: metadata, the step row, and where each lives in MCAP and HDF5.

Every writer (the MCAP and HDF5 sinks, convert, the session's row filler) and
every reader (replay, inspect, export, the viewer) goes through this module, so
the layout is written down in one place and a metadata key is never spelled
anywhere else.

Step row ("teleop.step.v1")
---------------------------
Every control step is one row of little-endian float64 values, in the order of
`StepLayout.fields`:

    time (1) | wall_time (1) | state (nstate) | ctrl (nu) | ee_target (n_arms*7)
    | ee_pose (n_arms*7) | qpos (nq) | qvel (nv) | gripper (n_arms) [| control (1)]

`state` is mj_getState(mjSTATE_INTEGRATION) taken before the step's ctrl is
written, so replay restores row 0 and re-steps with each ctrl. ee_target /
ee_pose are per arm x, y, z (m, world frame), qw, qx, qy, qz (MuJoCo's wxyz).
gripper is the commanded opening, 1 open .. 0 closed. `control` (schema 2 and
later, when the episode says so) says who drove the step: 0 a person or script,
1 a policy.

Metadata
--------
`EpisodeMeta`, a frozen dataclass. MCAP: a metadata record META_NAME holds every
field JSON-encoded (model XML and assets are attachments: MODEL_ATTACHMENT and
ASSET_PREFIX + name); a record META_END_NAME with the outcome (success,
complete, steps) is written at close; a file without it was cut short. HDF5
(robomimic layout): data/demo_0 attribute `teleop_meta` (JSON, every field but
the outcome), the outcome once as demo attrs success/complete/num_samples
(`closed` false: the file was cut short), `model_file` (XML), assets as uint8
datasets under data/demo_0/assets with attr `name`, `data.attrs["env_args"]`
from `EpisodeMeta.env_json`; per-step datasets in `HDF5_DATASETS`.

Schema version 1 files (before this module) load through `EpisodeMeta.from_json`
(`meta_from_mcap` / `meta_from_hdf5` add the outcome): their keys are the same,
`source` was not recorded (read as "human"), and HDF5 also copied the outcome
into `teleop_meta` and `env_args` at close.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from types import MappingProxyType
from typing import Any

import numpy as np

SCHEMA_VERSION = 2
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

SOURCES = ("human", "script", "generated", "policy")
CAMPAIGN_FIELDS = ("operator", "campaign", "session")  # optional provenance of campaign episodes
CONTROL_HUMAN, CONTROL_POLICY = 0.0, 1.0  # values of the `control` row field


# -- metadata ------------------------------------------------------------------


@dataclass(frozen=True)
class ArmMeta:
    """One arm as recorded: what IK drove and how the gripper maps to ctrl."""

    ee_site: str
    joints: tuple[str, ...]
    actuators: tuple[str, ...]  # position actuator per joint, same order
    home: tuple[float, ...]  # rad (or m for slide joints)
    gripper_actuator: str | None = None
    gripper_open: float | None = None  # ctrl value when open
    gripper_closed: float | None = None  # ctrl value when closed

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "ArmMeta":
        return cls(
            ee_site=str(d["ee_site"]),
            joints=tuple(d.get("joints") or ()),
            actuators=tuple(d.get("actuators") or ()),
            home=tuple(float(v) for v in d.get("home") or ()),
            gripper_actuator=d.get("gripper_actuator"),
            gripper_open=d.get("gripper_open"),
            gripper_closed=d.get("gripper_closed"),
        )


@dataclass(frozen=True)
class Outcome:
    """How an episode ended, known only at close (the META_END_NAME record)."""

    success: bool = False
    complete: bool = False  # False: cut short (Ctrl-C, a crash, a write error)
    steps: int | None = None
    recovered: bool = False  # rewritten by `teleop inspect --recover`

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass(frozen=True)
class EpisodeMeta:
    """Everything an episode file says about itself besides its steps.

    Sizes (nstate, nq, nv, nu) fix the step row; the model XML and assets
    rebuild the exact model; versions and machine say where bit-exact replay
    is promised. `source` says where the episode came from ("human" device,
    "script", "generated" from `source_episodes`, or a "policy" checkpoint) and
    `devices` which inputs drove it.
    """

    scene: str
    robot: str
    arms: tuple[ArmMeta, ...]
    nstate: int
    nq: int
    nv: int
    nu: int
    control_hz: float
    timestep: float  # s, physics step
    substeps: int  # physics steps per control tick
    seed: int = 0
    task: str = ""
    cameras: tuple[str, ...] = ()
    model_xml: str = field(default="", repr=False)
    assets: Mapping[str, bytes] = field(default_factory=dict, repr=False)
    mujoco_version: str = ""
    teleop_version: str = ""
    platform: str = ""
    machine: str = ""  # CPU architecture (exact replay is promised on the same one)
    python_version: str = ""
    start_time: str = ""  # ISO 8601, UTC
    episode_index: int = 0
    source: str = "human"
    devices: tuple[str, ...] = ()
    source_episodes: tuple[str, ...] = ()
    generator: Mapping[str, Any] | None = None
    policy: str | None = None
    # A collection campaign's episodes say who recorded them (issue 35); None elsewhere, and not written.
    operator: str | None = None
    campaign: str | None = None
    session: str | None = None
    records_control: bool = False  # rows carry the `control` field (who drove each step)
    outcome: Outcome = Outcome()
    schema_version: int = SCHEMA_VERSION
    extra: Mapping[str, Any] = field(default_factory=dict, repr=False)  # keys this version does not know

    def __post_init__(self) -> None:
        object.__setattr__(self, "assets", MappingProxyType(dict(self.assets)))
        object.__setattr__(self, "extra", MappingProxyType(dict(self.extra)))

    # -- derived --------------------------------------------------------------
    @property
    def n_arms(self) -> int:
        return max(len(self.arms), 1)

    @property
    def success(self) -> bool:
        return self.outcome.success

    @property
    def complete(self) -> bool:
        return self.outcome.complete

    @property
    def control_dt(self) -> float:
        """Seconds per control tick (what one recorded step covers)."""
        return self.timestep * self.substeps if self.timestep > 0 else 1.0 / self.control_hz

    @property
    def layout(self) -> "StepLayout":
        return StepLayout(self.nstate, self.nu, self.n_arms, self.nq, self.nv, self.records_control)

    def with_outcome(self, success: bool, complete: bool, steps: int | None = None, recovered: bool = False) -> "EpisodeMeta":
        return replace(self, outcome=Outcome(bool(success), bool(complete), steps, recovered))

    def replace(self, **changes: Any) -> "EpisodeMeta":
        return replace(self, **changes)

    # -- JSON ------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """Every field as plain JSON (model XML and assets left out: they are stored as files)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            if f.name in ("model_xml", "assets", "extra", "outcome", "arms"):
                continue
            value = getattr(self, f.name)
            if value is None and f.name in CAMPAIGN_FIELDS:
                continue
            out[f.name] = list(value) if isinstance(value, tuple) else (dict(value) if isinstance(value, Mapping) else value)
        out["robot_spec"] = {"name": self.robot, "arms": [_arm_json(a) for a in self.arms]}
        out["n_arms"] = self.n_arms
        out["step_layout"] = [list(x) for x in self.layout.fields]
        out.update(self.outcome.to_json())
        for key, value in self.extra.items():
            out.setdefault(key, value)
        return out

    def env_json(self) -> dict[str, Any]:
        """What describes the environment only (robomimic's `env_args.env_kwargs`): no outcome, no provenance."""
        keep = ("scene", "robot", "robot_spec", "seed", "task", "cameras", "control_hz", "timestep", "substeps",
                "nstate", "nq", "nv", "nu", "n_arms", "mujoco_version", "machine")
        full = self.to_json()
        return {k: full[k] for k in keep if k in full}

    @classmethod
    def from_json(cls, d: Mapping[str, Any], model_xml: str = "", assets: Mapping[str, bytes] | None = None) -> "EpisodeMeta":
        """Read metadata of any schema version (1 is migrated); raises KeyError/TypeError/ValueError if unusable."""
        d = dict(d)
        version = int(d.get("schema_version", 1))
        spec = d.get("robot_spec") or {}
        arms = tuple(ArmMeta.from_json(a) for a in spec.get("arms") or ())
        known = {f.name for f in fields(cls)} | {"robot_spec", "n_arms", "step_layout", "success", "complete", "steps", "recovered"}
        steps = d.get("steps")
        meta = cls(
            scene=str(d.get("scene", "")),
            robot=str(d.get("robot", spec.get("name", ""))),
            arms=arms,
            nstate=int(d["nstate"]),
            nq=int(d["nq"]),
            nv=int(d["nv"]),
            nu=int(d["nu"]),
            control_hz=float(d.get("control_hz") or 0.0),
            timestep=float(d.get("timestep") or 0.0),
            substeps=int(d.get("substeps") or 1),
            seed=int(d.get("seed") or 0),
            task=str(d.get("task") or ""),
            cameras=tuple(d.get("cameras") or ()),
            model_xml=model_xml or str(d.get("model_xml") or ""),
            assets=dict(assets if assets is not None else d.get("assets") or {}),
            mujoco_version=str(d.get("mujoco_version") or ""),
            teleop_version=str(d.get("teleop_version") or ""),
            platform=str(d.get("platform") or ""),
            machine=str(d.get("machine") or ""),
            python_version=str(d.get("python_version") or ""),
            start_time=str(d.get("start_time") or ""),
            episode_index=int(d.get("episode_index") or 0),
            # Version 1 did not say where an episode came from: every one was recorded from devices.
            source=str(d.get("source") or "human"),
            devices=tuple(d.get("devices") or ()),
            source_episodes=tuple(d.get("source_episodes") or ()),
            generator=d.get("generator"),
            policy=d.get("policy"),
            **{key: None if d.get(key) is None else str(d[key]) for key in CAMPAIGN_FIELDS},
            records_control=bool(d.get("records_control", False)),
            outcome=Outcome(bool(d.get("success", False)), bool(d.get("complete", False)),
                            None if steps is None else int(steps), bool(d.get("recovered", False))),
            schema_version=version,
            extra={k: v for k, v in d.items() if k not in known and k not in ("model_xml", "assets")},
        )
        n_arms = d.get("n_arms")
        if not arms and n_arms is not None and int(n_arms) != 1:
            raise ValueError(f"metadata says {n_arms} arms but describes none")
        recorded = d.get("step_layout")
        if recorded is not None and [tuple(x) for x in recorded] != meta.layout.fields:
            raise ValueError("recorded step layout does not match nstate/nq/nv/nu in the metadata")
        return meta


def _arm_json(arm: ArmMeta) -> dict[str, Any]:
    d = asdict(arm)
    d["joints"], d["actuators"], d["home"] = list(arm.joints), list(arm.actuators), list(arm.home)
    return d


def encode_mcap_meta(values: Mapping[str, Any]) -> dict[str, str]:
    """MCAP metadata records hold strings: each value JSON-encoded, so types survive."""
    return {k: json.dumps(v) for k, v in values.items()}


def decode_mcap_meta(record: Mapping[str, str]) -> dict[str, Any]:
    out = {}
    for key, value in record.items():
        try:
            out[key] = json.loads(value)
        except (TypeError, ValueError):
            out[key] = value
    return out


# -- the step row --------------------------------------------------------------

FIELDS = ("time", "wall_time", "state", "ctrl", "ee_target", "ee_pose", "qpos", "qvel", "gripper", "control")


@dataclass(frozen=True)
class StepLayout:
    """Where each field sits in a step row (float64 columns)."""

    nstate: int
    nu: int
    n_arms: int
    nq: int
    nv: int
    control: bool = False  # the optional `control` column (who drove the step)

    @property
    def fields(self) -> list[tuple[str, int]]:
        """(field, number of float64 values) in row order."""
        out = [
            ("time", 1), ("wall_time", 1), ("state", self.nstate), ("ctrl", self.nu),
            ("ee_target", self.n_arms * 7), ("ee_pose", self.n_arms * 7),
            ("qpos", self.nq), ("qvel", self.nv), ("gripper", self.n_arms),
        ]
        if self.control:
            out.append(("control", 1))
        return out

    @property
    def slices(self) -> dict[str, slice]:
        """Column slice of each field within a row."""
        out: dict[str, slice] = {}
        start = 0
        for name, size in self.fields:
            out[name] = slice(start, start + size)
            start += size
        return out

    @property
    def width(self) -> int:
        return sum(size for _, size in self.fields)

    def split(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """(T, width) rows -> named arrays: time/wall_time/control (T,), ee_* (T, n_arms, 7), others (T, n)."""
        cols = self.slices
        n = len(rows)
        out = {name: rows[:, cols[name]] for name, _ in self.fields}
        for scalar in ("time", "wall_time", "control"):
            if scalar in out:
                out[scalar] = out[scalar][:, 0]
        out["ee_target"] = out["ee_target"].reshape(n, self.n_arms, 7)
        out["ee_pose"] = out["ee_pose"].reshape(n, self.n_arms, 7)
        return out

    def join(self, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        """Named (T, ...) arrays -> (T, width) rows; the inverse of `split`. Missing wall_time/control are 0."""
        n = len(columns["time"])
        parts = []
        for name, size in self.fields:
            value = columns.get(name)
            if value is None or len(value) != n:
                if name not in ("wall_time", "control"):
                    raise ValueError(f"step field {name} is missing or has the wrong length")
                value = np.zeros(n)
            parts.append(np.asarray(value, dtype=np.float64).reshape(n, size))
        return np.ascontiguousarray(np.concatenate(parts, axis=1)) if parts else np.zeros((0, self.width))


# -- HDF5 (robomimic layout) ---------------------------------------------------

HDF5_DEMO = "data/demo_0"


@dataclass(frozen=True)
class Hdf5Dataset:
    """One per-step dataset under data/demo_0: its row field and trailing shape."""

    path: str
    field: str
    per_arm_pose: bool = False  # (T, n_arms, 7) rather than (T, n)


HDF5_DATASETS: tuple[Hdf5Dataset, ...] = (
    Hdf5Dataset("states", "state"),
    Hdf5Dataset("actions", "ctrl"),
    Hdf5Dataset("time", "time"),
    Hdf5Dataset("wall_time", "wall_time"),
    Hdf5Dataset("ee_target", "ee_target", per_arm_pose=True),
    Hdf5Dataset("ee_pose", "ee_pose", per_arm_pose=True),
    Hdf5Dataset("obs/qpos", "qpos"),
    Hdf5Dataset("obs/qvel", "qvel"),
    Hdf5Dataset("obs/gripper", "gripper"),
    Hdf5Dataset("control", "control"),
)
HDF5_LINKS = {"ctrl": "actions", "gripper": "obs/gripper"}  # names robomimic does not read, kept as soft links
HDF5_COMMANDS = "commands"  # one JSON list of device commands per step


def hdf5_shape(ds: Hdf5Dataset, layout: StepLayout) -> tuple[int, ...]:
    """Trailing shape of a dataset for this layout: () for scalars."""
    size = dict(layout.fields)[ds.field]
    if ds.per_arm_pose:
        return (layout.n_arms, 7)
    return () if ds.field in ("time", "wall_time", "control") else (size,)


def hdf5_datasets(layout: StepLayout) -> tuple[Hdf5Dataset, ...]:
    """The per-step datasets an episode with this layout has."""
    present = {name for name, _ in layout.fields}
    return tuple(d for d in HDF5_DATASETS if d.field in present)


# -- reading a file's metadata back -------------------------------------------


def meta_from_mcap(start: Mapping[str, Any], end: Mapping[str, Any] | None, model_xml: str,
                   assets: Mapping[str, bytes]) -> EpisodeMeta:
    """An MCAP episode's metadata from its start and end records (no end record: cut short)."""
    merged = dict(start)
    merged.update(end if end else {"success": False, "complete": False})
    return EpisodeMeta.from_json(merged, model_xml=model_xml, assets=assets)


def meta_from_hdf5(teleop_meta: Mapping[str, Any], model_xml: str, assets: Mapping[str, bytes],
                   success: bool | None, complete: bool | None, closed: bool, steps: int | None) -> EpisodeMeta:
    """An HDF5 episode's metadata: `teleop_meta` plus the demo's outcome attrs.

    An attr given as None is absent from the file: the value schema 1 copied into
    `teleop_meta` at close is used. A file never closed reads as cut short.
    """
    merged = dict(teleop_meta)
    for key, attr in (("success", success), ("complete", complete)):
        merged[key] = closed and bool(merged.get(key, False) if attr is None else attr)
    if closed and steps is not None:
        merged["steps"] = int(steps)
    return EpisodeMeta.from_json(merged, model_xml=model_xml, assets=assets)
