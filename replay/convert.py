"""Rewrite episode files: recover a crash-truncated MCAP, convert between MCAP and HDF5.

Output goes to a hidden temporary file next to OUT and is linked into place only
when complete, and never over an existing file: a failure leaves nothing behind.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from recorder import format as schema
from recorder.format import Outcome
from recorder.hdf5_sink import Hdf5Sink
from recorder.mcap_sink import McapSink
from replay.episode import Episode, EpisodeError, load_episode, sniff_format
from replay.mcap_read import McapScan, iter_records

TARGET_SUFFIXES = {"mcap": (".mcap",), "hdf5": (".hdf5", ".h5")}


class CutShortError(EpisodeError):
    """The episode to convert was cut short; `recoverable`: recover_mcap can make it whole first."""

    def __init__(self, message: str, recoverable: bool):
        super().__init__(message)
        self.recoverable = recoverable


def _check_out(out: Path, fmt: str | None = None) -> None:
    if out.exists() or out.is_symlink():
        raise EpisodeError(f"{out}: already exists, not overwriting")
    if not out.parent.is_dir():
        raise EpisodeError(f"{out.parent}: no such directory")
    if fmt is not None:
        other = [s for f, sfx in TARGET_SUFFIXES.items() if f != fmt for s in sfx]
        if out.suffix.lower() in other:
            raise EpisodeError(f"{out}: suffix {out.suffix} does not match format {fmt}")


def _publish(out: Path, build: Callable[[Path], None]) -> None:
    """Run build(tmp) then move tmp to out without ever replacing an existing file."""
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    tmp.unlink(missing_ok=True)
    try:
        build(tmp)
        try:
            os.link(tmp, out)  # fails if out appeared meanwhile
        except FileExistsError:
            raise EpisodeError(f"{out}: already exists, not overwriting") from None
        except OSError:  # filesystems without hard links
            if out.exists():
                raise EpisodeError(f"{out}: already exists, not overwriting") from None
            os.rename(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)


def recover_mcap(src: str | Path, out: str | Path) -> dict:
    """Copy every complete record of a (possibly footer-less) MCAP into a valid MCAP.

    A file that never got its end metadata gets one saying complete=false,
    success=false, so readers need not guess.
    """
    src, out = Path(src), Path(out)
    if sniff_format(src) != "mcap":
        raise EpisodeError(f"{src}: recovery works on MCAP files only")
    _check_out(out, "mcap")
    stats = {"messages": 0, "steps": 0, "source_truncated": False, "had_end_metadata": False}

    def build(tmp: Path) -> None:
        scan = McapScan()
        with open(tmp, "xb") as fh:
            w = Writer(fh, compression=CompressionType.ZSTD)
            w.start(profile="", library="teleop-recover")
            schema_ids: dict[int, int] = {0: 0}
            channel_ids: dict[int, int] = {}
            step_channels: set[int] = set()
            for rec in iter_records(src, scan):
                if isinstance(rec, Schema):
                    schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    channel_ids[rec.id] = w.register_channel(
                        rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0), rec.metadata
                    )
                    if rec.topic == schema.STEP_TOPIC:
                        step_channels.add(rec.id)
                elif isinstance(rec, Message) and rec.channel_id in channel_ids:
                    w.add_message(channel_ids[rec.channel_id], rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    stats["messages"] += 1
                    stats["steps"] += rec.channel_id in step_channels
                elif isinstance(rec, Attachment):
                    w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
                elif isinstance(rec, Metadata):
                    w.flush()  # keep file order: messages before it stay before it
                    w.add_metadata(rec.name, dict(rec.metadata))
                    stats["had_end_metadata"] |= rec.name == schema.META_END_NAME
            if not stats["had_end_metadata"]:
                end = Outcome(success=False, complete=False, steps=stats["steps"], recovered=True)
                w.flush()
                w.add_metadata(schema.META_END_NAME, schema.encode_mcap_meta(end.to_json()))
            w.finish()
        stats["source_truncated"] = scan.truncated

    _publish(out, build)
    return {"path": str(out), **stats}


def episode_rows(episode: Episode) -> np.ndarray:
    """The episode's steps back in packed row form (the layout's row order)."""
    columns = {
        "time": episode.time, "wall_time": episode.wall_time, "state": episode.state, "ctrl": episode.ctrl,
        "ee_target": episode.ee_target, "ee_pose": episode.ee_pose, "qpos": episode.qpos, "qvel": episode.qvel,
        "gripper": episode.gripper, "control": episode.control,
    }
    return episode.meta.layout.join(columns)


def write_episode(episode: Episode, out: str | Path, fmt: str) -> Path:
    """Write a loaded episode to a new file in `fmt` ("mcap" | "hdf5"), in the current schema version."""
    out = Path(out)
    if fmt not in TARGET_SUFFIXES:
        raise EpisodeError(f"unknown format {fmt!r}: use mcap or hdf5")
    _check_out(out, fmt)
    end = Outcome(episode.meta.success, episode.meta.complete, episode.steps)
    meta = episode.meta.replace(outcome=Outcome(), schema_version=schema.SCHEMA_VERSION)
    rows = episode_rows(episode)

    def build(tmp: Path) -> None:
        if fmt == "mcap":
            t0 = int(episode.wall_time[0] * 1e9) if episode.steps and len(episode.wall_time) else None
            sink = McapSink(tmp, meta, t0_ns=t0)
            sink.yield_s = 0.0  # nothing to share the GIL with
        else:
            sink = Hdf5Sink(tmp, meta)
        try:
            sink.write(rows, [json.dumps(c) if c else "[]" for c in episode.commands])
            sink.finish(end)
        except BaseException:
            sink.abort()
            raise

    _publish(out, build)
    return out


def convert_episode(src: str | Path, to: str, out: str | Path) -> dict:
    """`teleop convert`: refuses files cut short (recover those first)."""
    src, out = Path(src), Path(out)
    if to not in TARGET_SUFFIXES:
        raise EpisodeError(f"unknown format {to!r}: use mcap or hdf5")
    _check_out(out, to)
    episode = load_episode(src)
    if episode.truncated:
        if episode.format == "mcap":
            raise CutShortError(f"{src}: file is cut short ({episode.truncated_reason}); recover it first", True)
        raise CutShortError(f"{src}: file is cut short ({episode.truncated_reason}); its writer never closed it", False)
    episode.build_model()  # a file whose model does not compile is not worth converting
    write_episode(episode, out, to)
    return {"path": str(out), "format": to, "source": str(src), "steps": episode.steps}
