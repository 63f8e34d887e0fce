"""Export recorded episodes to a LeRobot dataset, rendering cameras from exact replay.

Works only from the recorded files and their stored model XML: each recorded
state is restored (mj_setState + mj_forward) and rendered offscreen, so any
camera at any size can be chosen after the fact and the teleop loop never paid
for rendering. Everything is written through LeRobot's own API
(`LeRobotDataset.create` / `resume`, `add_frame`, `save_episode`, `finalize`),
and `finalize` runs whatever happens, Ctrl-C included: an unfinalized dataset
loses every episode in its open parquet file.

LeRobot is an optional extra, imported only when an export starts.
"""

from __future__ import annotations

import json
import re
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path


from recorder.disk import check_free_space
from replay.episode import Episode, EpisodeError, find_episodes, load_episode
from replay.errors import first_line
from replay.export.frames import (
    ACTION_MODES, ENV_STATE, INTERVENTION, INTERVENTION_FEATURE, feature_key, features, is_channel_first, object_layout,
    robot_layout,
)
from replay.export.lerobot_io import ExportError, dir_size, load_lerobot
from replay.export.looks import COLUMN, Unit, dataset_has_column, record_column, units_of, variant
from replay.export.looks import check as check_looks
from replay.export.stats import image_stats
from replay.export.pieces import PIECE_EPISODES, export_in_pieces, is_interrupted
from replay.export.stream import EpisodeEnd, FrameStream
from replay.parallel.interrupts import is_cancelled, shielded
from replay.render import RenderError, warm_up
from scenes.extra_camera import CameraSpecError, ExtraCamera
from scenes.variation import VARIATION_KEY, Variation
from scenes.extra_camera import parse_cameras as parse_extra_cameras

DEFAULT_CAMERAS = ("front", "wrist")

# Video codecs, as LeRobot's RGBEncoderConfig settings. Measured on rendered 224x224 frames
# (GOP 2, as LeRobot sets): H.264 veryfast at CRF 20 gives AV1's PSNR (within 0.4 dB) at
# 1.1-1.2x its size, encodes in ~1 ms a frame instead of ~4.5 and decodes twice as fast when
# training reads it back. AV1 (LeRobot's own default) stays one flag away for the smallest files.
VIDEO_CODECS: dict[str, dict] = {
    "h264": {"vcodec": "h264", "preset": "veryfast", "crf": 20},
    "av1": {"vcodec": "libsvtav1"},
    "hevc": {"vcodec": "hevc", "preset": "veryfast", "crf": 24, "extra_options": {"x265-params": "log-level=error"}},
}
DEFAULT_CODEC = "h264"


@dataclass
class ExportOptions:
    out: Path
    repo_id: str
    cameras: list[str] | None = None  # None: front + wrist cameras where the scene has them
    image_size: tuple[int, int] = (224, 224)  # width, height
    action: str = "joint"
    task: str | None = None  # None: each episode's recorded task text
    only_success: bool = False
    video: bool = True
    vcodec: str | None = None  # a VIDEO_CODECS key; None: h264, or when appending what the dataset has
    append: bool = False
    progress: bool = True
    on_episode: Callable[[int, int], None] | None = None  # (episodes, frames) written so far, after each save
    workers: int = 1  # > 1: shards exported in that many processes, merged by LeRobot (replay/export/shards.py)
    ray: str | None = None  # "auto" or HOST:PORT / ray://HOST:PORT: the shards as tasks on a Ray cluster
    # The per-frame `intervention` feature (a person, not a policy, drove the frame). None: written when
    # an episode records who drove each step (a policy taken over in `teleop serve --policy`), or when
    # appending to a dataset that has it.
    intervention: bool | None = None
    # `observation.environment_state`: the task objects' poses in the robot's base frame (frames.py). When
    # appending, the dataset's own features decide.
    object_state: bool = True
    # Episodes are written in finalized pieces of this many (replay/export/pieces.py): a killed export
    # loses at most the piece in progress, and `resume` continues an interrupted one.
    piece_episodes: int = PIECE_EPISODES
    resume: bool = False
    force: bool = False  # go on when the free space looks too small for the rest (checked after the first piece)
    # Cameras added to each recorded model before rendering, as `NAME=pos:x,y,z;look_at:x,y,z[;fovy:deg]` (world frame,
    # m; scenes.extra_camera). Rendered besides the default cameras, or when `cameras` names them.
    add_cameras: tuple[str, ...] = ()
    # Looks (replay/export/looks.py): every episode rendered `looks` times, variant j with the look seed
    # variation.looks_seed + j; `variation.kinds` the looks that vary (none asked with looks > 1: lights, colors,
    # textures, cameras). One look and nothing to vary: the recorded look, today's export.
    looks: int = 1
    variation: Variation | None = None
    # The `variation` episode column (what each episode's look and physics were). None: written when looks vary,
    # an episode was generated with physics varied, or the dataset appended to has it.
    variation_meta: bool | None = None
    # A parallel export's shard: (index among the chosen episodes, look index or None) of the variants it exports.
    variant_plan: tuple[tuple[int, int | None], ...] | None = None
    # Leave out idle frames (replay/export/stream.py: action, robot state and objects' poses within IDLE_TOLERANCE
    # of the last frame kept): a person's pauses and the waits for a gripper, which teach a policy to stand still.
    drop_idle: bool = False

    @property
    def variation_key(self) -> dict | None:
        """What a resume must share of the looks (None: as recorded), for the export's journal."""
        if self.looks == 1 and self.variation is None:
            return None
        return {"looks": self.looks, **(self.variation.to_json() if self.variation is not None else {})}


@dataclass
class ExportSummary:
    out: Path
    episodes: int = 0  # written by this export
    frames: int = 0
    seconds: float = 0.0  # wall time of the export
    bytes: int = 0  # size of the dataset directory afterwards
    dataset_episodes: int = 0  # in the dataset afterwards (more than `episodes` when appending)
    fps: int = 0
    cameras: list[str] = field(default_factory=list)
    skipped_failed: int = 0
    skipped_empty: int = 0
    resumed_from: int = 0  # episodes an interrupted export had already written (--resume)
    interrupted: bool = False
    backend: str = ""
    looks: int = 1  # LeRobot episodes written per recorded one (each its own look)
    idle_dropped: int = 0  # idle frames left out (drop_idle)

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    def line(self) -> str:
        """The one-paragraph summary the CLI prints."""
        mb = self.bytes / 1e6
        text = (
            f"exported {self.episodes} episode{'s' * (self.episodes != 1)}, {self.frames} frames "
            f"({self.frames / self.fps if self.fps else 0:.1f} s at {self.fps} fps) in {self.seconds:.1f} s "
            f"({self.frames_per_s:.0f} frames/s) to {self.out} ({mb:.1f} MB, "
            f"{self.dataset_episodes} episode{'s' * (self.dataset_episodes != 1)} in all)"
        )
        if self.looks > 1:
            text += f"; {self.looks} looks of each recorded episode"
        if self.idle_dropped:
            share = self.idle_dropped / (self.idle_dropped + self.frames)
            text += f"; {self.idle_dropped} idle frames left out ({share:.0%})"
        if self.resumed_from:
            text += f"; resumed after the {self.resumed_from} episode{'s' * (self.resumed_from != 1)} already exported"
        skipped = []
        if self.skipped_failed:
            skipped.append(f"{self.skipped_failed} failed (only successful episodes kept)")
        if self.skipped_empty:
            skipped.append(f"{self.skipped_empty} empty")
        if skipped:
            text += "; skipped " + ", ".join(skipped)
        if self.interrupted:
            text += "; interrupted: the episodes above were saved, the one in progress was dropped"
        return text


def parse_image_size(text: str) -> tuple[int, int]:
    """'224x224' (width x height) -> (224, 224)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text or "")
    if not m or not (0 < int(m.group(1)) <= 4096 and 0 < int(m.group(2)) <= 4096):
        raise ExportError(f"image size {text!r}: expected WIDTHxHEIGHT, e.g. 224x224 (1 to 4096 pixels)")
    return int(m.group(1)), int(m.group(2))


def parse_cameras(text: str | None) -> list[str] | None:
    """'front,wrist' -> ['front', 'wrist']; 'none' or '' -> [] (no images); None -> default."""
    if text is None:
        return None
    names = [c.strip() for c in text.split(",") if c.strip()]
    return [] if names in ([], ["none"]) else names


# -- choosing what to export ------------------------------------------------


@dataclass
class _Entry:
    path: Path
    signature: tuple  # (robot, scene, control_hz): must agree across an export
    layout: tuple  # arms' joints/actuators: a same-named robot must also agree here
    success: bool
    complete: bool
    steps: int
    cameras: list[str]
    records_control: bool = False  # its steps say who drove (a policy or a person)
    varied: bool = False  # generated with physics varied (its metadata says how)


def _scan(paths: Iterable[str | Path]) -> list[_Entry]:
    try:
        files = find_episodes(list(paths))
    except EpisodeError as exc:
        raise ExportError(str(exc)) from None
    if not files:
        raise ExportError("no episode files (.mcap, .hdf5) in " + ", ".join(map(str, paths)))
    entries = []
    for f in files:
        try:
            ep = load_episode(f)
        except EpisodeError as exc:
            raise ExportError(str(exc)) from None
        m = ep.meta
        entries.append(
            _Entry(
                path=f,
                signature=(m.robot, m.scene, m.control_hz),
                layout=tuple((a.joints, a.actuators) for a in m.arms),
                success=m.success,
                complete=m.complete and not ep.truncated,
                steps=ep.steps,
                cameras=list(m.cameras),
                records_control=m.records_control,
                varied=VARIATION_KEY in m.extra,
            )
        )
    return entries


def _names(paths: list[Path], limit: int = 3) -> str:
    shown = ", ".join(p.name for p in paths[:limit])
    return shown + (f" and {len(paths) - limit} more" if len(paths) > limit else "")


def _check_consistent(entries: list[_Entry]) -> None:
    groups: dict[tuple, list[Path]] = {}
    for e in entries:
        groups.setdefault((*e.signature, e.layout), []).append(e.path)
    if len(groups) > 1:
        labels = [f"robot {k[0]} / scene {k[1]} / {k[2]:g} Hz" for k in groups]
        parts = [
            f"{label}{' (other joints)' if labels.count(label) > 1 else ''}: {_names(files)}"
            for label, files in zip(labels, groups.values())
        ]
        raise ExportError("episodes come from different robots, scenes or rates; export them separately: " + "; ".join(parts))


def resolve_cameras(wanted: list[str] | None, have: list[str]) -> list[str]:
    """Exact names, or a short name that matches one camera per arm (`wrist` -> `left/wrist`, `right/wrist`)."""
    explicit = wanted is not None
    out: list[str] = []
    for name in DEFAULT_CAMERAS if wanted is None else wanted:
        matches = [name] if name in have else [c for c in have if c.endswith("/" + name)]
        if not matches:
            if explicit:
                raise ExportError(f"unknown camera {name!r} (cameras: {', '.join(have) or 'none'})")
            continue
        out += [m for m in matches if m not in out]
    keys = [feature_key(c) for c in out]
    if len(set(keys)) != len(keys):
        raise ExportError(f"cameras {', '.join(out)} map to the same dataset key; choose fewer")
    return out


def _fps(hz: float) -> int:
    fps = round(hz)
    if fps <= 0 or abs(fps - hz) > 1e-6:
        raise ExportError(f"control rate {hz:g} Hz is not a whole number of frames per second, which LeRobot needs")
    return fps


# -- LeRobot ----------------------------------------------------------------


def video_decoder() -> tuple[str, str]:
    """(decoder, why not torchcodec) for LeRobot reading the dataset back; why is "" for torchcodec.

    Asked once here and handed to LeRobot: left to itself, LeRobot retries importing torchcodec
    for each dataset it opens and, where FFmpeg's shared libraries are missing, logs ~100 lines
    of loading tracebacks before falling back to PyAV, which works.
    """
    import importlib.util

    if importlib.util.find_spec("torchcodec") is None:
        return "pyav", "torchcodec not installed"
    try:
        import torchcodec  # noqa: F401
    except (ImportError, OSError, RuntimeError) as exc:
        text = str(exc)
        if re.search(r"libav\w*\.so\S*: cannot open shared object file", text):
            return "pyav", "torchcodec unavailable: FFmpeg's shared libraries (versions 4-8) not found"
        return "pyav", f"torchcodec unavailable: {first_line(exc)[:120]}"
    return "torchcodec", ""


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
    theirs = {k: v for k, v in meta.features.items() if k.startswith(("observation.", "action")) or k == INTERVENTION}
    for key in sorted(set(theirs) | set(spec)):
        a, b = theirs.get(key), spec.get(key)
        if a is None or b is None:
            problems.append(f"{key} {'missing there' if a is None else 'not exported here'}")
        elif a["dtype"] != b["dtype"] or tuple(a["shape"]) != tuple(b["shape"]) or list(a.get("names") or []) != list(b.get("names") or []):
            problems.append(f"{key} is {a['dtype']}{list(a['shape'])} there, {b['dtype']}{list(b['shape'])} here")
    if problems:
        raise ExportError(f"cannot append: {out} does not match these episodes: " + "; ".join(problems[:4]))


def _encoder(settings: dict):
    """LeRobot's RGB encoder config, or a one-line ExportError when this PyAV cannot encode it."""
    from lerobot.configs.video import RGBEncoderConfig

    try:
        return RGBEncoderConfig(**settings)
    except (ValueError, ImportError) as exc:
        raise ExportError(f"video codec {settings['vcodec']}: {first_line(exc)}") from None


def _dataset_encoder(meta, wanted: str | None, out: Path):
    """The encoder an existing dataset's videos were made with: appended episodes share its files."""
    from lerobot.configs.video import VIDEO_CODECS_ALIASES, encoder_config_from_video_info

    infos = [ft.get("info") or {} for ft in meta.features.values() if ft.get("dtype") == "video"]
    if not infos:
        return None
    stream = infos[0].get("video.codec")  # as the video stream names it: h264, hevc, av1
    encoder = VIDEO_CODECS_ALIASES.get(stream, stream)
    if wanted is not None and encoder and encoder != VIDEO_CODECS[wanted]["vcodec"]:
        raise ExportError(f"cannot append: {out} holds {stream} video; choose no video codec, or {stream}")
    try:
        return encoder_config_from_video_info(infos[0])
    except (ValueError, ImportError) as exc:
        raise ExportError(f"cannot append: cannot encode {out}'s video codec {stream}: {first_line(exc)}") from None


def _open_dataset(
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
            encoder = _dataset_encoder(meta, opts.vcodec, out)
            ds = LeRobotDataset.resume(
                opts.repo_id, root=out, image_writer_threads=0 if opts.video else 2, rgb_encoder=encoder, **common
            )
        except ExportError:
            raise
        except Exception as exc:  # noqa: BLE001 - LeRobot raises many kinds for a broken dataset
            first = first_line(exc)
            raise ExportError(f"cannot append: cannot open {out} as a LeRobot dataset: {first}") from None
        return ds, False
    encoder = _encoder(VIDEO_CODECS[opts.vcodec or DEFAULT_CODEC]) if opts.video else None
    ds = LeRobotDataset.create(
        opts.repo_id, fps, spec, root=out, robot_type=robot_type, use_videos=opts.video,
        image_writer_threads=0 if opts.video else 2, rgb_encoder=encoder, **common,
    )
    return ds, True


# -- the export -------------------------------------------------------------


def check_options(opts: ExportOptions) -> None:
    """The flags' own checks: they answer at once, before any file is read or LeRobot loads."""
    if opts.action not in ACTION_MODES:
        raise ExportError(f"action {opts.action!r}: choose one of {', '.join(ACTION_MODES)}")
    if opts.vcodec is not None and opts.vcodec not in VIDEO_CODECS:
        raise ExportError(f"video codec {opts.vcodec!r}: choose one of {', '.join(VIDEO_CODECS)}")
    if opts.vcodec is not None and not opts.video:
        raise ExportError("a video codec was chosen, but without video there is nothing to encode")
    if not opts.repo_id or not opts.repo_id.strip():
        raise ExportError("repo id must not be empty")
    if is_interrupted(opts.out) and not opts.resume:
        raise ExportError(f"{opts.out} holds an export that was interrupted: add --resume to continue it "
                          "(or remove the directory)")
    if opts.out.exists() and not opts.append and not opts.resume:
        raise ExportError(f"{opts.out} already exists (append the episodes to it, or choose a new directory)")
    if isinstance(opts.piece_episodes, bool) or not isinstance(opts.piece_episodes, int) or opts.piece_episodes < 1:
        raise ExportError(f"piece episodes {opts.piece_episodes!r}: expected a whole number of episodes, 1 or more")
    if opts.append and opts.out.exists() and not (opts.out / "meta" / "info.json").is_file():
        raise ExportError(f"cannot append: {opts.out} is not a LeRobot dataset (no meta/info.json)")
    if isinstance(opts.workers, bool) or not isinstance(opts.workers, int) or opts.workers < 1:
        raise ExportError(f"workers {opts.workers!r}: expected a whole number of processes, 1 or more")
    added_cameras(opts)
    check_looks(opts.looks, opts.variation)


def added_cameras(opts: ExportOptions) -> list[ExtraCamera]:
    """The cameras `opts.add_cameras` adds, parsed; ExportError (one line) for a malformed one."""
    try:
        specs = opts.add_cameras
        return parse_extra_cameras([specs] if isinstance(specs, str) else list(specs))
    except CameraSpecError as exc:
        raise ExportError(str(exc)) from None


def select_episodes(paths: list, opts: ExportOptions, log: Callable[[str], None]) -> tuple[list[_Entry], ExportSummary]:
    """The episodes to export, in order, and a summary with what was skipped, the fps and the cameras."""
    entries = _scan(paths)
    summary = ExportSummary(out=opts.out)
    chosen = []
    for e in entries:
        if opts.only_success and not e.success:
            summary.skipped_failed += 1
        elif e.steps == 0:
            summary.skipped_empty += 1
        else:
            chosen.append(e)
    if not chosen:
        why = f" ({summary.skipped_failed} did not succeed)" if summary.skipped_failed else ""
        raise ExportError(f"no episodes to export among {len(entries)} found{why}")
    _check_consistent(chosen)
    cut = [e.path for e in chosen if not e.complete]
    if cut:
        log(f"note: {len(cut)} episode(s) were cut short when recorded ({_names(cut)}); exporting the steps they have")
    summary.fps = _fps(chosen[0].signature[2])
    summary.looks = opts.looks
    added = [c.name for c in added_cameras(opts)]
    clash = [name for name in added if name in chosen[0].cameras]
    if clash:
        raise ExportError(f"camera {clash[0]!r}: the recordings already have a camera of that name (they keep their own "
                          "cameras; give the added one another name)")
    summary.cameras = resolve_cameras(opts.cameras, chosen[0].cameras + added)
    if opts.cameras is None:  # added cameras are rendered besides the default ones
        summary.cameras += [name for name in added if name not in summary.cameras]
    return chosen, summary


def export_serial(paths: Iterable[str | Path], opts: ExportOptions, log: Callable[[str], None] | None = None,
                  cancel: threading.Event | None = None) -> ExportSummary:
    """Export the episodes under `paths` into the LeRobot dataset at opts.out in this process, in finalized
    pieces (see module doc; `replay.export.export_dataset` chooses this or the parallel shards).

    cancel: a token (the CLI sets it on Ctrl-C). Once set, or on a KeyboardInterrupt, the
    export stops: the episode in progress is dropped, the saved ones are finalized and kept
    (`interrupted` in the summary). An episode being saved is saved whole first.
    """
    log = log or (lambda line: print(line, file=sys.stderr))
    paths = list(paths)
    check_options(opts)
    warm_up()  # the GL backend probe runs while episodes are scanned and LeRobot loads
    chosen, summary = select_episodes(paths, opts, log)
    opts = replace(opts, variation_meta=wants_variation_meta(opts, chosen))  # one answer for every piece
    units = export_units(chosen, opts)
    t0 = time.perf_counter()
    logs = [log]  # the first piece's notes (the video decoder) are the export's; the same again are not

    frames_left = [sum(u.steps for u in units)]  # not yet exported by this run
    per_frame: list[float] = []  # dataset bytes per frame, measured on the first piece this run writes

    def piece(paths: list[Unit], piece_opts: ExportOptions) -> ExportSummary:
        if per_frame and not opts.force:  # before the next piece: the rest must clearly fit (issue 25)
            check_free_space(opts.out, per_frame[0] * frames_left[0], f"{frames_left[0]} more frames of "
                             f"~{per_frame[0] / 1000:.1f} KB")
        size0 = dir_size(opts.out) if opts.out.exists() else 0
        done = _export_piece(paths, piece_opts, logs.pop() if logs else (lambda line: None), cancel)
        frames_left[0] -= done.frames
        if not per_frame and done.frames:
            per_frame.append(max(0, (dir_size(opts.out) if opts.out.exists() else 0) - size0) / done.frames)
        return done

    parts, summary.resumed_from = export_in_pieces(units, opts, piece, log, opts.piece_episodes, names=[u.name for u in units])
    for part in parts:
        summary.episodes += part.episodes
        summary.frames += part.frames
        summary.idle_dropped += part.idle_dropped
        summary.interrupted = summary.interrupted or part.interrupted
        summary.backend = summary.backend or part.backend
    summary.seconds = time.perf_counter() - t0
    summary.dataset_episodes = parts[-1].dataset_episodes if parts else summary.resumed_from
    summary.bytes = dir_size(opts.out) if opts.out.exists() else 0
    return summary


def export_units(chosen: list[_Entry], opts: ExportOptions) -> list[Unit]:
    """The LeRobot episodes to write, in order: each chosen episode once per look (a shard: its plan's)."""
    if opts.variant_plan is not None:
        return [Unit(chosen[i].path, chosen[i].steps, look) for i, look in opts.variant_plan]
    return units_of(chosen, opts.looks, opts.variation)


def wants_variation_meta(opts: ExportOptions, chosen: list[_Entry]) -> bool:
    """Whether the export writes the `variation` episode column: as resolved, else when looks vary, an episode was
    generated with physics varied, or the dataset appended to has it."""
    if opts.variation_meta is not None:
        return opts.variation_meta
    if opts.looks > 1 or opts.variation is not None or any(e.varied for e in chosen):
        return True
    return bool(opts.append and opts.out.exists() and dataset_has_column(opts.out))


def _export_piece(units: list[Unit], opts: ExportOptions, log: Callable[[str], None],
                  cancel: threading.Event | None) -> ExportSummary:
    """One finalized piece: the variants `units` into a new dataset, or appended to opts.out's."""
    paths = list(dict.fromkeys(u.path for u in units))
    chosen, summary = select_episodes(paths, replace(opts, only_success=False), lambda line: None)
    robot_type = chosen[0].signature[0]
    fps, cameras = summary.fps, summary.cameras
    LeRobotDataset = load_lerobot()  # after the input checks: they answer at once, LeRobot takes seconds to import
    decoder, why = video_decoder()

    first = load_episode(chosen[0].path)
    added = added_cameras(opts)
    try:
        model = first.build_model(added)
    except EpisodeError as exc:
        raise ExportError(str(exc)) from None
    try:
        arms = robot_layout(first.meta, model)
    except (KeyError, ValueError) as exc:
        raise ExportError(f"{first.path}: robot_spec does not match the recorded model: {exc}") from None
    objects = object_layout(first.meta, model) if wants_object_state(opts) else None
    spec = features(arms, opts.action, cameras, opts.image_size, opts.video, objects=objects)
    if wants_intervention(opts, chosen):
        spec[INTERVENTION] = dict(INTERVENTION_FEATURE)
    try:
        stream = FrameStream(model, opts.image_size, cameras)  # replays and renders in a thread of its own
    except RenderError as exc:
        raise ExportError(str(exc)) from None
    summary.backend = stream.backend
    # A streamed episode never waits on the encoder: its queue holds a whole episode.
    queue = max(e.steps for e in chosen) + 2
    t0 = time.perf_counter()
    column = wants_variation_meta(opts, chosen)
    if column and opts.append and opts.out.exists() and not dataset_has_column(opts.out):
        stream.close()
        raise ExportError(f"cannot append: {opts.out} has no per-episode {COLUMN} metadata, and these episodes vary "
                          "(their looks or physics); export them to a new dataset")
    try:
        ds, created = _open_dataset(LeRobotDataset, opts, spec, fps, robot_type, queue, decoder)
    except BaseException:
        stream.close()
        raise
    if why and opts.video and cameras:  # once the export goes ahead: an error stays the one line
        log(f"video: {decoder} decoder ({why})")  # slower reads in training, nothing wrong
    try:
        with image_stats():  # LeRobot's per-frame image statistics, from value counts (replay/export/stats.py)
            _write(ds, units, first, opts, cameras, stream, summary, cancel, column)
    except KeyboardInterrupt:
        summary.interrupted = True
    finally:
        _finish(ds, stream)
        summary.seconds = time.perf_counter() - t0
        if created and summary.episodes == 0 and opts.out.exists():
            shutil.rmtree(opts.out, ignore_errors=True)  # nothing saved: leave no half dataset behind
    summary.dataset_episodes = ds.meta.total_episodes
    summary.bytes = dir_size(opts.out) if opts.out.exists() else 0
    return summary


def _appended_features(opts: ExportOptions) -> dict | None:
    """The features of the dataset an append goes into, or None (not appending, or no dataset yet)."""
    info = opts.out / "meta" / "info.json"
    if not (opts.append and info.is_file()):
        return None
    try:
        return json.loads(info.read_text()).get("features") or {}
    except (OSError, ValueError):
        return None


def wants_object_state(opts: ExportOptions) -> bool:
    """Whether the export writes `observation.environment_state`: as asked, or as the dataset appended to has it."""
    existing = _appended_features(opts)
    return opts.object_state if existing is None else ENV_STATE in existing


def wants_intervention(opts: ExportOptions, chosen: list[_Entry]) -> bool:
    """Whether the export writes `intervention`: as asked, else when an episode records who drove
    each step, or the dataset appended to already has the feature."""
    if opts.intervention is not None:
        return opts.intervention
    if any(e.records_control for e in chosen):
        return True
    info = opts.out / "meta" / "info.json"
    if opts.append and info.is_file():
        try:
            return INTERVENTION in (json.loads(info.read_text()).get("features") or {})
        except (OSError, ValueError):
            return False
    return False


def _loader(path: Path) -> Callable[[], Episode]:
    def load() -> Episode:
        try:
            return load_episode(path)
        except EpisodeError as exc:  # changed on disk since the scan
            raise ExportError(str(exc)) from None

    return load


def _loaders(units: list[Unit], first: Episode) -> list[Callable[[], Episode]]:
    """One loader per variant; the variants of one episode share its one load."""
    last = {"path": units[0].path, "episode": first}

    def loader(path: Path) -> Callable[[], Episode]:
        def load() -> Episode:
            if last["path"] != path:
                last["episode"], last["path"] = None, path
                last["episode"] = _loader(path)()
            return last["episode"]

        return load

    return [loader(u.path) for u in units]


def _write(ds, chosen: list[Unit], first: Episode, opts: ExportOptions, cameras, stream: FrameStream,
           summary: ExportSummary, cancel: threading.Event | None, column: bool = False) -> None:
    """LeRobot's side: add the stream's frames, save each episode as its last frame arrives.

    `chosen`: the variants, in order; `column`: write each one's `variation` episode metadata.
    Cancelled (the token, or a KeyboardInterrupt), it ends with KeyboardInterrupt between
    frames; the episode in progress is dropped.
    """
    from tqdm import tqdm

    keys = [feature_key(c) for c in cameras]
    channel_first = [is_channel_first(ds.meta.features[k]) for k in keys]  # as the dataset declares them
    added = tuple(added_cameras(opts))
    prepare = None
    if column or any(u.look is not None for u in chosen):
        prepare = [(lambda ep, model, look=u.look: variant(ep, model, look, opts.looks, opts.variation, added)) for u in chosen]
    next_variation = record_column(ds) if column else None
    stream.start(_loaders(chosen, first), opts.action, lambda ep: opts.task or ep.meta.task or ep.meta.scene or "task", keys,
                 channel_first, intervention=INTERVENTION in ds.meta.features, objects=ENV_STATE in ds.meta.features,
                 cameras_added=added, prepare=prepare, drop_idle=opts.drop_idle)
    total = sum(e.steps for e in chosen)
    bar = tqdm(total=total, unit="frame", desc=f"episode 1/{len(chosen)}", disable=not opts.progress,
               file=sys.stderr, dynamic_ncols=True)
    try:
        for item in stream:
            if is_cancelled(cancel):
                raise KeyboardInterrupt
            if not isinstance(item, EpisodeEnd):
                ds.add_frame(item)
                bar.update(1)
                continue
            if next_variation is not None:
                next_variation(item.variation or {})
            # LeRobot's save_episode writes data, video and metadata in turn; cut in between, the
            # dataset would hold frames its metadata does not know of: a Ctrl-C waits for it.
            _, interrupted = shielded(ds.save_episode)
            summary.episodes += 1
            summary.frames += item.steps
            summary.idle_dropped += item.dropped
            bar.update(item.dropped)  # the bar counts recorded steps
            if item.index + 1 < len(chosen):
                bar.set_description(f"episode {item.index + 2}/{len(chosen)}")
            if opts.on_episode is not None:
                opts.on_episode(summary.episodes, summary.frames)
            if interrupted or is_cancelled(cancel):
                raise KeyboardInterrupt
    except BaseException:
        try:
            pending = ds.has_pending_frames()
        except KeyError:  # the buffer was half taken apart by save_episode (LeRobot pops its "size")
            pending = True
        if pending:  # the episode in progress is dropped, the saved ones stay
            ds.clear_episode_buffer()
        raise
    finally:
        bar.close()


def _finish(ds, stream: FrameStream) -> None:
    """Stop the stream, then finalize(), with a Ctrl-C held meanwhile: cutting it short would lose saved episodes."""

    def finish() -> None:
        try:
            stream.close()
        finally:
            ds.finalize()

    shielded(finish)
