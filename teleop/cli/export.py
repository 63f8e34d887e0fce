"""`teleop export`: recorded episodes -> a LeRobot dataset, cameras rendered from exact replay."""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

from teleop.errors import UsageError
from teleop.cli.signals import cancel_on_interrupt
from teleop.cli.variation_args import LOOKS_WORDS, add_looks_seed_arg, add_range_args, variation_from


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser(
        "export",
        help="export recorded episodes to a LeRobot dataset (camera images rendered from exact replay)",
        description="Export recorded episodes to a LeRobot dataset. Camera images are rendered by "
        "replaying the recorded states, so any camera at any size can be chosen now.",
    )
    p.add_argument("paths", nargs="+", type=Path, metavar="PATHS", help="episode files or directories of them")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="dataset directory (must not exist unless --append)")
    p.add_argument("--repo-id", default=None, metavar="NAME", help="dataset name, e.g. me/panda_lift (required unless --preview)")
    p.add_argument(
        "--cameras", default=None, metavar="LIST",
        help="comma list of cameras to render; 'wrist' means every arm's wrist camera; 'none' for no images "
        "(default: front,wrist where the scene has them)",
    )
    p.add_argument(
        "--camera", action="append", default=[], metavar="SPEC",
        help="add a fixed camera to the recorded model before rendering (repeatable): "
        "'NAME=pos:x,y,z;look_at:x,y,z[;fovy:deg]', world frame in m (robot base at the origin, table top z=0), "
        "fovy default 45. Rendered besides the default cameras, or when --cameras names it",
    )
    p.add_argument("--image-size", default="224x224", metavar="WxH", help="image width x height (default 224x224)")
    p.add_argument(
        "--action", default="joint", choices=("joint", "ee_delta", "ee_pose"),
        help="action: joint position targets + gripper (default); ee_delta: commanded EE target minus the "
        "current EE pose (world frame, m and rotation vector rad) + gripper; ee_pose: commanded EE pose "
        "(xyz + quat wxyz) + gripper. Gripper: 1 open .. 0 closed",
    )
    p.add_argument("--task", default=None, metavar="TEXT", help="task text for every frame (default: each episode's recorded task)")
    p.add_argument("--only-success", action="store_true", help="skip episodes that did not succeed at their task")
    p.add_argument("--accepted", action="store_true",
                   help="only episodes with an accept verdict (teleop review: <episode>.review.json); the dataset's "
                   "episode metadata then carries each one's verdict, reviewer and quality flags")
    p.add_argument("--reject-flags", default=None, metavar="FLAG[,FLAG]",
                   help="leave out episodes with any of these quality flags (docs/review.md: long, idle, jerky, "
                   "wandering, tracking, chatter, dropped, hard_contact, failed, not_exact)")
    p.add_argument("--operator", default=None, metavar="NAME[,NAME]",
                   help="export only the episodes these operators recorded (a collection campaign's episodes name "
                   "theirs; the dataset's episode metadata gets an `operator` column)")
    p.add_argument("--no-video", action="store_true", help="store camera frames as PNG images instead of MP4 video")
    p.add_argument(
        "--vcodec", default=None, choices=("h264", "av1", "hevc"),
        help="video codec: h264 (default: fast to encode and to decode in training), av1 (LeRobot's "
        "default, smallest files, ~4x slower to encode), hevc. With --append: the dataset's own codec",
    )
    p.add_argument(
        "--no-object-state", action="store_true",
        help="leave out observation.environment_state (each task object's position and wxyz quaternion in the "
        "robot's base frame, written by default). With --append: the dataset's own features decide",
    )
    p.add_argument(
        "--drop-idle", action="store_true",
        help="leave out idle frames: those whose action, robot state and objects' poses are all within 1e-3 (rad, m, "
        "quaternion, gripper fraction) of the last frame kept, such as a person's pauses and the waits for a gripper "
        "(a policy trained on them learns to stand still); a slow motion is kept at a lower rate",
    )
    p.add_argument("--append", action="store_true", help="add the episodes to the existing dataset at --out")
    p.add_argument(
        "--resume", action="store_true",
        help="continue an export that was interrupted (killed, Ctrl-C, a full disk) with the same episodes and "
        "options: what its finished pieces wrote is kept, the piece in progress is written again",
    )
    p.add_argument(
        "--force", action="store_true",
        help="go on even when the free space looks too small for the rest (checked after the first piece)",
    )
    p.add_argument(
        "--piece-episodes", default="20", metavar="N",
        help="episodes per finalized piece (default 20): a killed export loses at most the piece in progress",
    )
    p.add_argument(
        "--workers", default="1", metavar="K",
        help="export shards of the episodes in K processes at once, then merge them with LeRobot's "
        "aggregation (default 1: one process). Not with --append",
    )
    p.add_argument(
        "--ray", default=None, metavar="ADDRESS",
        help="export the shards as tasks on a Ray cluster: 'auto' (the one running on this machine's network), "
        "HOST:PORT or ray://HOST:PORT; --workers K then sets the tasks at once (default: the cluster's CPUs). "
        "Needs .[cluster]; the nodes need this package installed, not the episode files",
    )
    p.add_argument(
        "--looks", default="1", metavar="K",
        help="render each episode K times, each with its own seeded look (lights, colours, textures, camera jitter), as K "
        "LeRobot episodes with the same actions and states (default 1: the recorded look). The looks that vary: --vary",
    )
    p.add_argument("--vary", default=None, metavar="WORDS",
                   help=f"the looks to vary, comma list of {LOOKS_WORDS} (default with --looks > 1: looks)")
    add_range_args(p, textures=True)
    add_looks_seed_arg(p, "look seed of the first look (variant j uses S + j; training seeds, apart from teleop eval's "
                       "held-out ones; default 0)")
    p.add_argument("--preview", default=None, metavar="N",
                   help="write no dataset: a contact sheet (PNG at --out FILE.png) of N looks of the first episode's first "
                   "frame, a row per camera")
    p.set_defaults(func=cmd_export)


def quiet_environment() -> None:
    """Before LeRobot loads: export is local (never wait on the Hub), and ours is the one progress bar."""
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("HF_DATASETS_DISABLE_PROGRESS_BARS", "1")
    # ...which `datasets` then warns about each time LeRobot opens a dataset to append to.
    warnings.filterwarnings("ignore", message="Cannot enable progress bars", category=UserWarning)
    quiet = "ignore:Cannot enable progress bars:UserWarning"  # ...and in the export's worker processes, which start anew
    if quiet not in os.environ.get("PYTHONWARNINGS", ""):
        os.environ["PYTHONWARNINGS"] = ",".join(w for w in (os.environ.get("PYTHONWARNINGS", ""), quiet) if w)
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 encoder: errors only, no banner per video


def _count(text: str, flag: str, what: str) -> int:
    """A whole number >= 1 for `flag`, checked here so a bad value is the one error line (argparse adds its usage)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise UsageError(f"{flag} {text!r}: expected a whole number of {what}, 1 or more")
    return value


def _workers(text: str) -> int:
    return _count(text, "--workers", "processes")


def cmd_export(args: argparse.Namespace) -> int:
    quiet_environment()
    from replay.export import ExportError, ExportOptions
    from replay.export.operators import parse_operators
    from replay.export.options import parse_image_size
    from replay.features import parse_cameras
    from replay.export import export_dataset
    from scenes.cameras.extra import CameraSpecError, parse_cameras as parse_extra_cameras

    try:
        parse_extra_cameras(args.camera)  # a malformed --camera answers at once, before any file is read
    except CameraSpecError as exc:
        raise UsageError(f"--camera: {exc}") from None
    variation = variation_from(args, "export")  # a bad word, range or texture file: one line, at once
    preview = _count(args.preview, "--preview", "looks") if args.preview is not None else None
    if preview is None and not args.repo_id:
        raise UsageError("--repo-id is required (a dataset name, e.g. me/panda_lift)")
    try:
        opts = ExportOptions(
            out=args.out,
            repo_id=args.repo_id or "preview/looks",
            cameras=parse_cameras(args.cameras),
            image_size=parse_image_size(args.image_size),
            action=args.action,
            task=args.task,
            only_success=args.only_success,
            video=not args.no_video,
            vcodec=args.vcodec,
            append=args.append,
            progress=sys.stderr.isatty(),
            workers=_workers(args.workers),
            ray=args.ray,
            object_state=not args.no_object_state,
            resume=args.resume,
            piece_episodes=_count(args.piece_episodes, "--piece-episodes", "episodes"),
            force=args.force,
            add_cameras=tuple(args.camera),
            looks=_count(args.looks, "--looks", "looks"),
            variation=variation,
            drop_idle=args.drop_idle,
            operators=parse_operators(args.operator),
            accepted=args.accepted,
            reject_flags=tuple(w.strip() for w in (args.reject_flags or "").split(",") if w.strip()),
        )
        if preview is not None:
            from replay.export.preview import contact_sheet

            sheet = contact_sheet(args.paths, opts, preview)
            print(f"wrote {preview} looks of {Path(sheet['episode']).name}'s first frame ({', '.join(sheet['cameras'])}) "
                  f"to {sheet['out']} ({sheet['size'][0]}x{sheet['size'][1]})")
            return 0
        with cancel_on_interrupt() as cancel:  # Ctrl-C: the episode being saved ends whole, the saved ones stay
            summary = export_dataset(args.paths, opts, cancel=cancel)
    except ExportError as exc:
        raise UsageError(str(exc)) from None
    print(summary.line())
    return 130 if summary.interrupted else 0
