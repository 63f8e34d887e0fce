"""`teleop robots`, `teleop scenes`, `teleop run` (headless session) and `teleop bench`."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from devices.base import Cautioned, Device, Restartable
from devices.registry import DeviceOptions, open_devices
from recorder import RecorderError
from scenes import BUILTIN_ROBOTS
from scenes.catalog import catalog
from scenes.errors import TeleopError
from teleop.errors import UsageError
from teleop.cli.json_output import print_json
from teleop.cli.variation_args import add_physics_args, variation_from
from teleop.cli.signals import interrupts_ignored
from teleop.control.loop import run_episode
from teleop.control.recording import Recorder
from teleop.control.session import Session


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("robots", help="list the built-in robots")
    p.set_defaults(func=cmd_robots)
    p = sub.add_parser("scenes", help="list every task (built-in and library, or the task files given) and the robots it fits")
    p.add_argument("paths", nargs="*", metavar="PATH.toml", help="task files to check and list (default: every built-in and library task)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(func=cmd_scenes)

    p = sub.add_parser("run", help="run a session headless (scripted or keyboard/SpaceMouse) and print a summary")
    add_session_args(p)
    p.add_argument("--device", required=True, help="comma list: script:FILE.json, keyboard, spacemouse")
    p.add_argument("--seconds", type=float, default=None, help="simulated seconds per episode (default: until the script ends)")
    p.add_argument("--episodes", type=int, default=1, help="episodes to run, seeds seed, seed+1, ... (default 1)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("bench", help="measure the speed figures the issues name")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true", help="fewer repetitions (rougher figures)")
    p.add_argument("--only", default=None,
                   help="comma list of bench modules to run (control, recording, web, export, devices, generate, eval, cameras)")
    p.set_defaults(func=cmd_bench)


def add_session_args(p: argparse.ArgumentParser) -> None:
    """Flags shared by `run` and `serve`."""
    p.add_argument("--scene", default="lift", help="task scene (default lift; see `teleop scenes`)")
    p.add_argument("--robot", default="panda", help="built-in robot name or PATH.toml (default panda)")
    p.add_argument("--seed", type=int, default=0, help="object placement seed (default 0)")
    p.add_argument("--control-hz", type=float, default=30.0, help="control rate in Hz (default 30)")
    p.add_argument("--record", type=Path, default=None, metavar="DIR", help="record episodes into DIR")
    p.add_argument("--format", default="mcap", choices=("mcap", "hdf5", "both"), help="recording format (default mcap)")
    p.add_argument("--no-verify", action="store_true", help="skip the exact-replay check after each saved episode")
    p.add_argument("--pos-speed", type=float, default=0.15, help="hold-to-move speed, m/s (default 0.15)")
    p.add_argument("--rot-speed", type=float, default=0.8, help="hold-to-rotate speed, rad/s (default 0.8)")
    add_physics_args(p)


def cmd_robots(args: argparse.Namespace) -> int:
    width = max(len(n) for n in BUILTIN_ROBOTS)
    for name, (summary, _) in BUILTIN_ROBOTS.items():
        print(f"{name:<{width}}  {summary}")
    return 0


def cmd_scenes(args: argparse.Namespace) -> int:
    """Every task with its instruction, family, objects and the robots it builds with (each robot is built)."""
    rows = catalog(list(args.paths) or None)
    if args.json:
        print_json({"task_count": len(rows), "scenes": rows})
        return 0
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        px = "; ".join(f"{c} {v['object_px_at_96']:g} px" for c, v in r.get("cameras", {}).items() if c in ("front", "overhead"))
        print(f"{r['name']:<{width}}  [{r['family']}] {r['instruction']}  objects: {', '.join(r['objects'])}; "
              f"robots: {', '.join(r['robots']) or 'none'}" + (f"; smallest object at 96x96: {px}" if px else ""))
    return 0


def make_session(args: argparse.Namespace, verify: str = "sync", on_error: str = "raise") -> Session:
    """A Session from the shared flags, with a Recorder attached when --record is given."""
    if args.record is not None and args.record.exists() and not args.record.is_dir():
        raise UsageError(f"--record {args.record}: exists and is not a directory")
    variation = variation_from(args, "generation")  # a bad --vary word or range: one line, before the scene builds
    session = Session(scene=args.scene, robot=args.robot, seed=args.seed, control_hz=args.control_hz, variation=variation)
    if args.record is not None:
        formats = ("mcap", "hdf5") if args.format == "both" else (args.format,)
        Recorder(session, args.record, formats, verify="off" if args.no_verify else verify, on_error=on_error)
    return session


def open_session_devices(args: argparse.Namespace, n_arms: int, serving: bool = False,
                         log: Callable[[str], None] | None = None) -> tuple[list[Device], list[str]]:
    """The devices of --device (one way for run and serve); problems and caveats go to `log`.

    Serving, a session may start with no device but the page (the gizmo comes and goes with
    browsers), and a misspelt device name is an error rather than a line in the device list.
    """
    log = log or (lambda m: print(m, file=sys.stderr))
    if args.pos_speed <= 0 or args.rot_speed <= 0:
        raise UsageError("--pos-speed and --rot-speed must be positive")
    options = DeviceOptions(pos_speed=args.pos_speed, rot_speed=args.rot_speed, n_arms=n_arms)
    devices, problems = open_devices(args.device, options, require_any=not serving, require_known=serving)
    for line in problems:
        log(f"device not started: {line}")
    for device in devices:
        if isinstance(device, Cautioned) and device.warning:
            log(f"{device.name}: {device.warning}")
    return devices, problems


def cmd_run(args: argparse.Namespace) -> int:
    if args.episodes < 1:
        raise UsageError("--episodes must be at least 1")
    if args.seconds is not None and args.seconds <= 0:
        raise UsageError("--seconds must be positive")
    log = (lambda m: print(m, file=sys.stderr)) if args.json else print
    session = make_session(args)
    devices, _ = open_session_devices(args, session.n_arms)
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
            result = run_episode(session, devices, seconds=args.seconds, realtime=not scripted)  # people drive in real time
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
        "ik_failures": session.ik_failures,
        "ee_tracking_error_mm": episodes[-1]["ee_tracking_error_mm"] if len(episodes) == 1 else _merged_error(episodes),
        "targets_clamped": session.clamped,
        "interrupted": interrupted,
        "devices": [d.name for d in devices],
    }
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
        for f in summary.get("files", []):
            print(f"recorded {f}")
        for m in session.messages:
            print(f"note: {m}")
    return 130 if interrupted else 0


def _merged_error(episodes: list[dict]) -> dict:
    meds = [e["ee_tracking_error_mm"]["median"] for e in episodes if e["ee_tracking_error_mm"]["median"] is not None]
    maxs = [e["ee_tracking_error_mm"]["max"] for e in episodes if e["ee_tracking_error_mm"]["max"] is not None]
    if not meds:
        return {"median": None, "max": None}
    return {"median": round(float(np.median(meds)), 3), "max": round(float(max(maxs)), 3)}


def cmd_bench(args: argparse.Namespace) -> int:
    """Run the checkout's bench/ (not installed with the package) in a fresh process and pass its figures on."""
    root = Path(__file__).resolve().parents[2]
    if not (root / "bench" / "run.py").is_file():
        raise UsageError("the bench needs a source checkout: bench/ is not installed with the package")
    benches = sorted(p.stem for p in (root / "bench").glob("*.py") if "\ndef measure(" in p.read_text())  # bench modules
    unknown = [w.strip() for w in (args.only or "").split(",") if w.strip() and w.strip() not in benches]
    if unknown:
        raise UsageError(f"--only {','.join(unknown)}: unknown bench (benches: {', '.join(benches)})")
    flags = [*(["--quick"] if args.quick else []), *(["--only", args.only] if args.only else []), "--json"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run([sys.executable, "-m", "bench.run", *flags], cwd=root, env=env, stdout=subprocess.PIPE,
                          stderr=None, text=True)
    if done.returncode != 0:
        raise UsageError(f"the bench failed (exit {done.returncode}); its output is above")
    try:
        results = json.loads(done.stdout)
    except ValueError:
        raise UsageError("the bench printed something other than its figures on stdout") from None
    if args.json:
        print_json(results)
    else:
        for key, value in results.items():
            print(f"{key:<28} {value}")
    return 0
