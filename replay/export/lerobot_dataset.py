"""Opening the LeRobot dataset an export writes: a new one, or an existing one to append to, checked
first (fps, robot, features, video codec) so a dataset that does not fit is never opened for writing.

LeRobot is an optional extra: the caller hands in its `LeRobotDataset` class (lerobot_io.load_lerobot).
"""

from __future__ import annotations

from pathlib import Path

from replay.errors import first_line
from replay.export.codecs import DEFAULT_CODEC, VIDEO_CODECS, dataset_encoder, new_encoder
from replay.export.lerobot_io import ExportError
from replay.export.options import ExportOptions
from replay.export.review_meta import SUBTASK_INDEX
from replay.features import INTERVENTION, is_channel_first


def _match_image_layout(spec: dict, theirs: dict) -> None:
    """Declare our cameras in the existing dataset's channel order (older exports are (H, W, 3))."""
    for key, ft in spec.items():
        other = theirs.get(key)
        if ft["dtype"] not in ("image", "video") or other is None or len(other.get("shape") or ()) != 3:
            continue
        if is_channel_first(other) != is_channel_first(ft):
            shape = ft["shape"]
            ft["shape"] = (shape[1], shape[2], shape[0]) if is_channel_first(ft) else (shape[2], shape[0], shape[1])
            ft["names"] = list(other["names"])


def _check_appendable(meta, spec: dict, fps: int, robot_type: str, out: Path) -> None:
    _match_image_layout(spec, meta.features)
    problems = []
    if meta.fps != fps:
        problems.append(f"fps {meta.fps} there, {fps} here")
    if meta.robot_type != robot_type:
        problems.append(f"robot {meta.robot_type} there, {robot_type} here")
    theirs = {k: v for k, v in meta.features.items() if k.startswith(("observation.", "action")) or k in (INTERVENTION, SUBTASK_INDEX)}
    for key in sorted(set(theirs) | set(spec)):
        a, b = theirs.get(key), spec.get(key)
        if a is None or b is None:
            problems.append(f"{key} {'missing there' if a is None else 'not exported here'}")
        elif a["dtype"] != b["dtype"] or tuple(a["shape"]) != tuple(b["shape"]) or list(a.get("names") or []) != list(b.get("names") or []):
            problems.append(f"{key} is {a['dtype']}{list(a['shape'])} there, {b['dtype']}{list(b['shape'])} here")
    if problems:
        raise ExportError(f"cannot append: {out} does not match these episodes: " + "; ".join(problems[:4]))


def open_dataset(
    LeRobotDataset, opts: ExportOptions, spec: dict, fps: int, robot_type: str, queue: int, decoder: str
):
    """(dataset, created) for opts.out: a new dataset, or the existing one when appending."""
    out = opts.out
    # One thread per camera's encoder: cameras already encode in parallel, and more threads
    # only fight the renderer for the cores.
    common = dict(streaming_encoding=opts.video, encoder_queue_maxsize=queue, encoder_threads=1, video_backend=decoder)
    if out.exists():
        if not opts.append:
            raise ExportError(f"{out} already exists (append the episodes to it, or choose a new directory)")
        if not (out / "meta" / "info.json").is_file():
            raise ExportError(f"cannot append: {out} is not a LeRobot dataset (no meta/info.json)")
        from lerobot.datasets import LeRobotDatasetMetadata

        try:  # read-only first: a dataset that does not fit is never opened for writing
            meta = LeRobotDatasetMetadata(opts.repo_id, root=out)
            _check_appendable(meta, spec, fps, robot_type, out)
            encoder = dataset_encoder(meta, opts.vcodec, out)
            ds = LeRobotDataset.resume(
                opts.repo_id, root=out, image_writer_threads=0 if opts.video else 2, rgb_encoder=encoder, **common
            )
        except ExportError:
            raise
        except Exception as exc:  # noqa: BLE001 - LeRobot raises many kinds for a broken dataset
            first = first_line(exc)
            raise ExportError(f"cannot append: cannot open {out} as a LeRobot dataset: {first}") from None
        return ds, False
    encoder = new_encoder(VIDEO_CODECS[opts.vcodec or DEFAULT_CODEC]) if opts.video else None
    ds = LeRobotDataset.create(
        opts.repo_id, fps, spec, root=out, robot_type=robot_type, use_videos=opts.video,
        image_writer_threads=0 if opts.video else 2, rgb_encoder=encoder, **common,
    )
    return ds, True

