"""`teleop run`: a session headless (scripted, keyboard or SpaceMouse), then a summary of what it did."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from scenes.errors import TeleopError
from teleop.errors import UsageError
from teleop.cli.json_output import print_json
from teleop.cli.session_args import add_session_args, devices_from, follower_from, session_from
from teleop.cli.signals import interrupts_ignored


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser("run", help="run a session headless (scripted or keyboard/SpaceMouse) and print a summary")
    add_session_args(p)
    p.add_argument("--device", required=True,
                   help="comma list: script:FILE.json, instruct:SENTENCE, keyboard, spacemouse, so101_leader:PORT[:id=NAME...] (and "
                        "so100_leader, koch_leader: docs/leaders.md)")
    p.add_argument("--seconds", type=float, default=None, help="simulated seconds per episode (default: until the script ends)")
    p.add_argument("--episodes", type=int, default=1, help="episodes to run, seeds seed, seed+1, ... (default 1)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(func=cmd_run)


def cmd_run(args: argparse.Namespace) -> int:
    from devices.base import Restartable  # here, not above: `teleop --help` needs none of MuJoCo or mink
    from recorder import RecorderError
    from scenes.workers import shielded
    from teleop.control.loop import run_episode

    if args.episodes < 1:
        raise UsageError("--episodes must be at least 1")
    if args.seconds is not None and args.seconds <= 0:
        raise UsageError("--seconds must be positive")
    log = (lambda m: print(m, file=sys.stderr)) if args.json else print
    session = session_from(args)
    follower = follower_from(args, session)  # a real arm mirroring the simulated one (--follower), or None
    try:
        devices, _ = devices_from(args, session.controller.n_arms, session=session)
    except BaseException:
        if follower is not None:
            follower.close()
        raise
    scripted = all(d.kind == "script" for d in devices)
    if args.seconds is None and not scripted:
        log("running until Ctrl-C (give --seconds to stop by itself)")
    episodes = []
    wall_start = time.perf_counter()
    interrupted = False
    try:
        for episode in range(args.episodes):
            if episode > 0:
                session.reset(args.seed + episode)
            for d in devices:
                if isinstance(d, Restartable):
                    d.restart()
            # people drive in real time, and a real follower moves in it
            result = run_episode(session, devices, seconds=args.seconds, realtime=not scripted or follower is not None)
            entry = {
                "seed": result.seed,
                "steps": result.steps,
                "sim_seconds": result.sim_seconds,
                "success": result.success,
                "ik_failures": result.ik_failures,
                "ee_tracking_error_mm": result.ee_tracking_error_mm,
                "files": [str(p) for p in result.files],
            }
            if result.replay_bit_exact is not None:
                entry["replay_bit_exact"] = result.replay_bit_exact
            episodes.append(entry)
    except KeyboardInterrupt:
        interrupted = True
        with interrupts_ignored():  # a second Ctrl-C must not cut the save short
            session.close()
        log("interrupted: the episode in progress was saved, marked incomplete")
    except RecorderError as exc:
        raise UsageError(f"recording failed: {exc}") from None
    except TeleopError:
        session.close()
        raise
    finally:
        for d in devices:
            d.close()
        if follower is not None:
            follower_status = follower.status()  # as it was while the session ran
            shielded(follower.close)  # stop sending, torque off, however the session ended (a 2nd Ctrl-C waits)
    wall = time.perf_counter() - wall_start
    summary = {
        "scene": args.scene,
        "robot": session.robot.name,
        "seed": args.seed,
        "control_hz": session.control_hz,
        "episodes": len(episodes),
        "steps": sum(e["steps"] for e in episodes),
        "sim_seconds": round(sum(e["sim_seconds"] for e in episodes), 6),
        "wall_seconds": round(wall, 4),
        "success": bool(episodes) and all(e["success"] for e in episodes),
        "ik_failures": session.stats.ik_failures,
        "ee_tracking_error_mm": episodes[-1]["ee_tracking_error_mm"] if len(episodes) == 1 else _merged_error(episodes),
        "targets_clamped": session.stats.clamped,
        "interrupted": interrupted,
        "devices": [d.name for d in devices],
    }
    if follower is not None:
        summary["follower"] = follower_status
    if args.record:
        summary["files"] = [f for e in episodes for f in e["files"]]
        summary["record_dir"] = str(args.record)
    if len(episodes) > 1:
        summary["per_episode"] = episodes
    if args.json:
        print_json(summary)
    else:
        err = summary["ee_tracking_error_mm"]
        print(
            f"{summary['robot']} on {summary['scene']}: {summary['steps']} steps, {summary['sim_seconds']:.2f} s simulated "
            f"in {summary['wall_seconds']:.2f} s, success={summary['success']}, IK failures={summary['ik_failures']}, "
            f"EE tracking error median {err['median']} mm / max {err['max']} mm"
        )
        if follower is not None:
            f = summary["follower"]
            gap = "" if f["max_gap_deg"] is None else f", gap {f['max_gap_deg']} deg"
            print(f"follower {f['port']}: {f['state']}{gap}; {f['sent']} goals sent, {f['clamped']} clamped to its range")
        for f in summary.get("files", []):
            print(f"recorded {f}")
        for m in session.stats.messages:
            print(f"note: {m}")
    return 130 if interrupted else 0


def _merged_error(episodes: list[dict]) -> dict:
    meds = [e["ee_tracking_error_mm"]["median"] for e in episodes if e["ee_tracking_error_mm"]["median"] is not None]
    maxs = [e["ee_tracking_error_mm"]["max"] for e in episodes if e["ee_tracking_error_mm"]["max"] is not None]
    if not meds:
        return {"median": None, "max": None}
    return {"median": round(float(np.median(meds)), 3), "max": round(float(max(maxs)), 3)}
