"""`teleop video` and `teleop review`: look at episodes as a reviewer does.

`video` renders episodes from their exact replay into an MP4 or GIF with the
overlay strip (replay.review.video); `review` serves one page for a folder of
episodes where verdicts are recorded (teleop.web.review_page.server). Errors a user
can cause (no episode, a camera the episode lacks, an unwritable path, a full
disk) end as one line and exit code 2.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from teleop.cli.access_args import add_access_args
from teleop.cli.json_output import print_json
from teleop.cli.signals import cancel_on_interrupt
from teleop.errors import UsageError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser("video", help="render episodes from their exact replay into an MP4 (H.264) or GIF",
                       description="Frames from each recorded state, the cameras side by side, one frame per control "
                       "step, with a strip: instruction, time, subtask, who drives, success.")
    p.add_argument("paths", nargs="+", type=Path, metavar="EPISODE|DIR", help="episode files or folders of them")
    p.add_argument("--out", required=True, type=Path, metavar="FILE", help="the video: FILE.mp4 or FILE.gif")
    p.add_argument("--camera", default=None, metavar="NAMES",
                   help="comma list of the episode's cameras (default: front,wrist where it has them)")
    p.add_argument("--size", default="320x240", metavar="WxH", help="each camera's image size (default 320x240)")
    p.add_argument("--fps", type=float, default=None, metavar="N",
                   help="frames per second of the video (default: the episode's control rate, real time)")
    p.add_argument("--grid", action="store_true",
                   help="tile several episodes in one video (the shorter ones hold their last frame); "
                        "without it they play one after another")
    p.add_argument("--no-overlay", action="store_true", help="no strip under the frames")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(func=cmd_video)

    p = sub.add_parser("review", help="review a folder of episodes in the browser: videos, quality flags, verdicts",
                       description="One page: every episode with a thumbnail, task, source, success, duration, "
                       "flags and verdict; keys j/k move, a accepts, r rejects, n adds a note. Verdicts go to "
                       "<episode>.review.json beside each episode.")
    p.add_argument("folder", type=Path, metavar="DIR", help="a folder of episode files")
    add_access_args(p)
    p.set_defaults(func=cmd_review)


def cmd_video(args: argparse.Namespace) -> int:
    from replay.render import rasterize_in_render_threads
    from replay.review.encode import VideoError, check_writable
    from replay.review.video import VideoOptions, parse_size, write_video

    rasterize_in_render_threads()  # each camera renders in a thread of its own

    try:
        check_writable(args.out)
        cameras = tuple(c.strip() for c in args.camera.split(",") if c.strip()) if args.camera else ()
        if args.fps is not None and not 0 < args.fps <= 1000:
            raise UsageError(f"--fps {args.fps:g}: must be more than 0 and at most 1000")
        options = VideoOptions(cameras=cameras, size=parse_size(args.size), fps=args.fps, grid=args.grid,
                               overlay=not args.no_overlay)
        result = write_video(args.paths, args.out, options)
    except VideoError as exc:
        raise UsageError(str(exc)) from None
    if args.json:
        print_json(result)
    else:
        print(f"wrote {result['out']}: {result['frames']} frames at {result['fps']:g} fps, "
              f"{result['width']}x{result['height']} ({result['frames_per_s']} frames/s)")
    return 0


def cmd_review(args: argparse.Namespace) -> int:
    from replay.render import rasterize_in_render_threads
    from teleop.web.shared.access import resolve_token
    from teleop.web.review_page.server import serve_review

    rasterize_in_render_threads()  # videos and thumbnails render in the page's request threads

    token = resolve_token(args.host, args.token, args.no_token)  # a bad combination: one line, exit 2, at once
    if not args.folder.is_dir():
        raise UsageError(f"{args.folder}: not a folder of episodes")
    # Ctrl-C and SIGTERM stop the server, even when started with SIGINT ignored (as a background job).
    with cancel_on_interrupt(even_if_ignored=True) as stop:
        return serve_review(args.folder, args.host, args.port, token=token, no_token=args.no_token, stop=stop,
                            log=lambda line: print(line, flush=True))

