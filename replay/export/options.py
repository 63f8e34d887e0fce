"""What an export is asked to do: `ExportOptions` (the flags), their own checks, the CLI's strings
parsed, and `ExportSummary`, what it did.

New options are new fields with a default (the rest of the export reads them by name), checked in
`check_options` where they can be checked before any file is read.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from replay.export.codecs import VIDEO_CODECS
from replay.export.lerobot_io import ExportError
from replay.export.looks import check as check_looks
from replay.export.pieces import PIECE_EPISODES, is_interrupted
from replay.export.review_meta import NOT_ACCEPTED, parse_flags
from replay.features import ACTION_MODES
from scenes.cameras.extra import CameraSpecError, ExtraCamera
from scenes.cameras.extra import parse_cameras as parse_extra_cameras
from scenes.vary.variation import Variation


@dataclass
class ExportOptions:
    """The export's settings, one field per `teleop export` flag (sizes in pixels, rates in Hz)."""

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
    # m; scenes.cameras.extra). Rendered besides the default cameras, or when `cameras` names them.
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
    # Only the episodes these operators recorded (campaign episodes name theirs; replay/export/operators.py).
    operators: tuple[str, ...] | None = None
    # The `operator` episode column. None: written when an episode names its operator, or the dataset appended to has it.
    operator_meta: bool | None = None
    # Review (replay/export/review_meta.py): keep only episodes with an accept verdict, leave out those with any of
    # these quality flags; the dataset's episode metadata then carries each one's verdict, reviewer and flags.
    accepted: bool = False
    reject_flags: tuple[str, ...] = ()
    # Resolved once per export (export_dataset) for every piece and shard: each episode's review and subtasks
    # (review_meta.Extras by review_meta.episode_key), and the subtasks' texts in index order.
    extras: dict | None = None
    subtasks: tuple[str, ...] = ()

    @property
    def variation_key(self) -> dict | None:
        """What a resume must share of the looks (None: as recorded), for the export's journal."""
        if self.looks == 1 and self.variation is None:
            return None
        return {"looks": self.looks, **(self.variation.to_json() if self.variation is not None else {})}


@dataclass
class ExportSummary:
    """What an export did: counts, timing, size, and what it skipped (the CLI's summary line, --json)."""

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
    left_out: dict[str, int] = field(default_factory=dict)  # left out by review: why ("not accepted", a flag) -> episodes

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
        for why, count in self.left_out.items():
            skipped.append(f"{count} {why}" if why == NOT_ACCEPTED else f"{count} flagged {why}")
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
    parse_flags(opts.reject_flags)


def added_cameras(opts: ExportOptions) -> list[ExtraCamera]:
    """The cameras `opts.add_cameras` adds, parsed; ExportError (one line) for a malformed one."""
    try:
        specs = opts.add_cameras
        return parse_extra_cameras([specs] if isinstance(specs, str) else list(specs))
    except CameraSpecError as exc:
        raise ExportError(str(exc)) from None

