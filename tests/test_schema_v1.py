"""Schema 1 files (written before recorder/format.py) still load into EpisodeMeta, replay bit-exact and convert.

The old files are made here the way the old writer laid them out: one metadata
dict (the keys below, the outcome false at the start), in MCAP a start record
and an end record with the outcome; in HDF5 the dict in `teleop_meta` and
`env_args` with the outcome copied into both at close, and no next_obs.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from recorder.format import META_END_NAME, META_NAME, SCHEMA_VERSION, EpisodeMeta
from replay import load_episode, resimulate
from replay.convert import convert_episode
from replay.summary import summarize
from teleop.cli.entry import main
from tests.support import record_pusher_episode

STEPS = 60
ROW_FIELDS = ("time", "wall_time", "state", "ctrl", "ee_target", "ee_pose", "qpos", "qvel", "gripper")


def old_dict(meta: EpisodeMeta) -> dict:
    """The schema 1 metadata dict, key by key as the old session and writer filled it (no model or assets)."""
    arms = [{"ee_site": a.ee_site, "joints": list(a.joints), "actuators": list(a.actuators),
             "gripper_actuator": a.gripper_actuator, "gripper_open": a.gripper_open,
             "gripper_closed": a.gripper_closed, "home": list(a.home)} for a in meta.arms]
    nstate, nu, nq, nv = meta.nstate, meta.nu, meta.nq, meta.nv
    return {
        "schema_version": 1, "scene": meta.scene, "robot": meta.robot,
        "robot_spec": {"name": meta.robot, "arms": arms},
        "mujoco_version": meta.mujoco_version, "teleop_version": "dev", "platform": meta.platform,
        "machine": meta.machine, "python_version": meta.python_version, "seed": meta.seed,
        "control_hz": meta.control_hz, "timestep": meta.timestep, "substeps": meta.substeps, "task": meta.task,
        "cameras": list(meta.cameras), "nstate": nstate, "nq": nq, "nv": nv, "nu": nu,
        "start_time": meta.start_time, "episode_index": meta.episode_index,
        "n_arms": len(arms),
        "step_layout": [["time", 1], ["wall_time", 1], ["state", nstate], ["ctrl", nu], ["ee_target", 7 * len(arms)],
                        ["ee_pose", 7 * len(arms)], ["qpos", nq], ["qvel", nv], ["gripper", len(arms)]],
        "success": False, "complete": False,
    }


def write_v1_mcap(src: Path, out: Path, old: dict, end: dict | None) -> None:
    """Copy an MCAP record by record, with the schema 1 start record, and `end` (None: none) as the end record."""
    with open(src, "rb") as fh, open(out, "xb") as dst:
        w = Writer(dst, compression=CompressionType.ZSTD)
        w.start(profile="", library="teleop-recorder")
        schemas, channels = {0: 0}, {}
        for rec in StreamReader(fh).records:
            if isinstance(rec, Schema):
                schemas[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
            elif isinstance(rec, Channel):
                channels[rec.id] = w.register_channel(rec.topic, rec.message_encoding, schemas[rec.schema_id], rec.metadata)
            elif isinstance(rec, Message):
                w.add_message(channels[rec.channel_id], rec.log_time, rec.data, rec.publish_time, rec.sequence)
            elif isinstance(rec, Attachment):
                w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            elif isinstance(rec, Metadata) and rec.name == META_NAME:
                w.add_metadata(META_NAME, {k: json.dumps(v) for k, v in old.items()})
        if end is not None:
            w.flush()
            w.add_metadata(META_END_NAME, {k: json.dumps(v) for k, v in end.items()})
        w.finish()


def write_v1_hdf5(src: Path, out: Path, old: dict, end: dict) -> None:
    """An HDF5 file as schema 1 closed it: the outcome in teleop_meta and env_args too, no next_obs."""
    shutil.copy(src, out)
    closed = {**old, **end}
    with h5py.File(out, "r+") as f:
        f["data"].attrs["env_args"] = json.dumps({"env_name": old["scene"], "type": 0, "env_kwargs": closed})
        demo = f["data/demo_0"]
        demo.attrs["teleop_meta"] = json.dumps(closed)
        demo.attrs["schema_version"] = 1
        del demo["next_obs"], demo.attrs["next_obs_final"]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    directory = tmp_path_factory.mktemp("v1")
    new = {p.suffix[1:]: p for p in record_pusher_episode(directory / "new", 0, steps=STEPS, seed=2)}
    old = old_dict(load_episode(new["mcap"]).meta)
    end = {"success": True, "complete": True, "steps": STEPS}
    out = {f"new_{k}": p for k, p in new.items()}
    out["mcap"], out["hdf5"], out["cut"] = directory / "old.mcap", directory / "old.hdf5", directory / "cut.mcap"
    write_v1_mcap(new["mcap"], out["mcap"], old, end)
    write_v1_hdf5(new["hdf5"], out["hdf5"], old, end)
    write_v1_mcap(new["mcap"], out["cut"], old, None)
    return out


@pytest.mark.parametrize("fmt", ["mcap", "hdf5"])
def test_schema_1_loads_with_the_same_values(files, fmt):
    old, new = load_episode(files[fmt]), load_episode(files[f"new_{fmt}"])
    assert isinstance(old.meta, EpisodeMeta) and old.meta.schema_version == 1 and new.meta.schema_version == SCHEMA_VERSION
    assert old.meta.success is True and old.meta.complete is True and old.meta.outcome.steps == STEPS
    assert old.meta.source == "human"  # schema 1 did not say; every file then came from devices
    assert old.meta.teleop_version == "dev" and not old.meta.extra
    same = new.meta.replace(schema_version=1, source="human", teleop_version="dev")
    assert old.meta == same
    assert old.meta.model_xml == new.meta.model_xml and old.meta.arms == new.meta.arms
    for name in ROW_FIELDS:
        assert np.array_equal(getattr(old, name), getattr(new, name)), name
    assert old.commands == new.commands and not old.truncated


def test_schema_1_mcap_without_end_record_reads_as_cut_short(files):
    ep = load_episode(files["cut"])
    assert ep.meta.success is False and ep.meta.complete is False and ep.meta.outcome.steps is None
    assert ep.steps == STEPS and not ep.truncated


@pytest.mark.parametrize("fmt", ["mcap", "hdf5"])
def test_schema_1_inspect_json_says_what_the_file_says(files, fmt, capsys):
    assert main(["inspect", str(files[fmt]), "--json"]) == 0
    old = json.loads(capsys.readouterr().out)
    new = summarize(load_episode(files[f"new_{fmt}"]))
    assert old.keys() == new.keys()
    assert old["schema_version"] == 1 and old["success"] is True and old["complete"] is True
    # version 1 did not record where an episode came from: it reads as "human", with no devices named
    assert old["source"] == "human" and old["devices"] == []
    skip = ("path", "schema_version", "source", "devices")
    assert {k: v for k, v in old.items() if k not in skip} == {k: v for k, v in new.items() if k not in skip}


@pytest.mark.parametrize("fmt,to", [("mcap", "hdf5"), ("hdf5", "mcap")])
def test_schema_1_replays_bit_exact_and_converts_to_the_current_schema(files, fmt, to, tmp_path):
    old = load_episode(files[fmt])
    assert resimulate(old, warn=False).bit_exact
    out = tmp_path / f"converted.{to}"
    convert_episode(files[fmt], to, out)
    conv = load_episode(out)
    assert conv.meta.schema_version == SCHEMA_VERSION
    assert conv.meta == old.meta.replace(schema_version=SCHEMA_VERSION)  # the same meaning, in the current schema
    for name in ROW_FIELDS:
        assert np.array_equal(getattr(conv, name), getattr(old, name)), name
    assert conv.commands == old.commands
    assert resimulate(conv, warn=False).bit_exact
