"""`teleop inspect`, `teleop convert`, `teleop replay`: look at, rewrite and replay recorded episodes.

Readers raise replay.EpisodeError with a one-line message; here it becomes a
UsageError (exit 2). Nothing is ever written over an existing file.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from teleop.errors import UsageError
from teleop.cli.access_args import add_access_args
from teleop.cli.json_output import print_json
from teleop.cli.signals import cancel_on_interrupt


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser("inspect", help="summarize a recorded episode (works on files cut short by a crash)")
    p.add_argument("path", type=Path, metavar="PATH", help="episode file (.mcap or .hdf5)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.add_argument("--recover", type=Path, default=None, metavar="OUT",
                   help="rewrite a truncated MCAP into a valid one at OUT (every complete message)")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("convert", help="convert an episode between MCAP and HDF5")
    p.add_argument("path", type=Path, metavar="PATH", help="episode file (.mcap or .hdf5)")
    p.add_argument("--to", required=True, choices=("hdf5", "mcap"), help="output format")
    p.add_argument("out", type=Path, metavar="OUT", help="output file (must not exist)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("replay", help="replay an episode: restore its states or re-simulate its ctrl")
    p.add_argument("path", type=Path, metavar="PATH", help="episode file (.mcap or .hdf5)")
    p.add_argument("--mode", choices=("state", "action"), default=None,
                   help="state: restore every recorded state; action: restore the first and re-simulate ctrl "
                        "(default: action with --verify, else state)")
    p.add_argument("--verify", action="store_true",
                   help="compare every re-simulated state bit for bit; exit 0 only when exact")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.add_argument("--serve", action="store_true", help="open the episode in the browser viewer instead")
    add_access_args(p, host="viewer host", port="viewer port", when="with --serve: ")
    p.set_defaults(func=cmd_replay)


def _load(path: Path):
    from replay import EpisodeError, load_episode

    try:
        return load_episode(path)
    except EpisodeError as exc:
        raise UsageError(str(exc)) from None


def _emit(obj: dict, as_json: bool) -> None:
    if as_json:
        print_json(obj)
        return
    for key, value in obj.items():
        print(f"{key}: {json.dumps(value) if isinstance(value, (dict, list)) else value}")


def cmd_inspect(args: argparse.Namespace) -> int:
    from replay.convert import recover_mcap
    from replay import EpisodeError
    from replay.summary import summarize

    if args.recover is not None and (args.recover.exists() or args.recover.is_symlink()):
        raise UsageError(f"--recover {args.recover}: already exists, not overwriting")
    episode = _load(args.path)
    summary = summarize(episode)
    if args.recover is not None:
        if episode.format != "mcap":
            raise UsageError(f"{args.path}: --recover works on MCAP files only")
        try:
            summary["recovered"] = recover_mcap(args.path, args.recover)
        except EpisodeError as exc:
            raise UsageError(str(exc)) from None
        except OSError as exc:
            raise UsageError(f"{args.recover}: cannot write: {exc.strerror or exc}") from None
    _emit(summary, args.json)
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from replay.convert import CutShortError, convert_episode
    from replay import EpisodeError

    try:
        result = convert_episode(args.path, args.to, args.out)
    except CutShortError as exc:
        hint = f" with: teleop inspect {args.path} --recover OUT" if exc.recoverable else ""
        raise UsageError(f"{exc}{hint}") from None
    except EpisodeError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"{args.out}: cannot write: {exc.strerror or exc}") from None
    if args.json:
        print_json(result)
    else:
        print(f"converted {args.path} -> {args.out} ({args.to}, {result['steps']} steps)")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from replay import EpisodeError, replay_states, resimulate

    mode = args.mode or ("action" if args.verify else "state")
    if args.verify and mode != "action":
        raise UsageError("--verify re-simulates: use it with --mode action")
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port {args.port}: must be 0..65535")
    if (args.token is not None or args.no_token) and not args.serve:
        raise UsageError("--token and --no-token are for the viewer: add --serve")
    token = None
    if args.serve:
        from teleop.web.shared.access import resolve_token

        token = resolve_token(args.host, args.token, args.no_token)  # a bad combination: one line, exit 2, at once
    episode = _load(args.path)
    try:
        model = episode.build_model()
    except EpisodeError as exc:
        raise UsageError(str(exc)) from None
    if args.serve:
        try:
            from teleop.web.replay_page.viewer import serve_episode
        except ImportError as exc:
            raise UsageError(f"the episode viewer is not available: {exc}") from None
        # Ctrl-C and SIGTERM stop the viewer, even when started with SIGINT ignored (as a background job).
        with cancel_on_interrupt(even_if_ignored=True) as stop:
            return int(serve_episode(episode, args.host, args.port, token=token, no_token=args.no_token, stop=stop))

    out: dict = {"path": str(args.path), "mode": mode, "steps": episode.steps, "seconds": episode.seconds,
                 "truncated": episode.truncated}
    if mode == "state":
        t0 = time.perf_counter()
        for _ in replay_states(episode, model):
            pass
        wall = time.perf_counter() - t0
        out.update(bit_exact=None, max_abs_diff=None, first_divergence_step=None, wall_seconds=round(wall, 6),
                   states_per_s=round(episode.steps / wall, 1) if wall > 0 else None)
        code = 0
    else:
        result = resimulate(episode, verify=True, model=model)
        d = result.to_dict()
        out.update(
            bit_exact=d["bit_exact"], max_abs_diff=d["max_abs_diff"], first_divergence_step=d["first_divergence_step"],
            compared=d["compared"], wall_seconds=round(d["wall_seconds"], 6),
            realtime_factor=None if d["realtime_factor"] is None else round(d["realtime_factor"], 2),
            warnings=d["warnings"],
        )
        code = 0 if (result.bit_exact or not args.verify) else 1
    if args.json:
        print_json(out)
    elif mode == "state":
        print(f"restored {episode.steps} recorded states in {out['wall_seconds']:.3f} s")
    elif out["bit_exact"]:
        print(f"re-simulated {episode.steps} steps ({episode.seconds:.2f} s): bit-exact")
    else:
        print(
            f"re-simulated {episode.steps} steps ({episode.seconds:.2f} s): diverged at step "
            f"{out['first_divergence_step']} (max |diff| {out['max_abs_diff']:.3g})",
            file=sys.stdout,
        )
    return code
