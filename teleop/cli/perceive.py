"""`teleop perceive`: where the camera finds each object of a scene, beside the truth (teleop.instruct.perceive)."""

from __future__ import annotations

import argparse
from pathlib import Path

from teleop.cli.json_output import print_json
from teleop.errors import UsageError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser("perceive", help="find a scene's objects in a rendered RGB-D view; print estimate, truth and error",
                       description="Render one RGB-D view of the scene at a seed, find each object of the task file by its "
                                   "colour, back-project its pixels to a world position, and print it beside the true one. "
                                   "Saves the view with the detections drawn.")
    p.add_argument("--scene", default="lift", help="task scene (default lift; see `teleop scenes`)")
    p.add_argument("--robot", default="panda", help="built-in robot name or PATH.toml (default panda)")
    p.add_argument("--seed", type=int, default=0, help="object placement seed (default 0)")
    p.add_argument("--camera", default="front", help="the scene's camera to look through (default front)")
    p.add_argument("--size", type=int, default=224, metavar="PX", help="square image side in pixels (default 224)")
    p.add_argument("--image", type=Path, default=None, metavar="PATH.png",
                   help="where to save the view with the detections drawn (default perceive-SCENE-SEED.png)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(func=cmd_perceive)


def cmd_perceive(args: argparse.Namespace) -> int:
    if not 16 <= args.size <= 4096:
        raise UsageError("--size must be 16..4096 pixels")
    image = args.image or Path(f"perceive-{args.scene}-{args.seed}.png")
    if image.suffix.lower() != ".png":
        raise UsageError(f"--image {image}: must be a .png file")
    from PIL import Image

    from teleop.control.session import Session
    from teleop.instruct.compare import compared
    from teleop.instruct.perceive import draw

    session = Session(scene=args.scene, robot=args.robot, seed=args.seed, control_hz=30.0)
    try:
        seen, rows = compared(session.controller, args.camera, args.size, args.size)
    finally:
        session.close()
    try:
        Image.fromarray(draw(seen)).save(image)
    except OSError as exc:
        raise UsageError(f"--image {image}: cannot write it ({exc.strerror or exc})") from None
    out = {"objects": rows, "camera": args.camera, "scene": args.scene, "robot": session.robot.name, "seed": args.seed,
           "size": [args.size, args.size], "image": str(image), "perceive_ms": round(seen.ms, 2)}
    if args.json:
        print_json(out)
        return 0
    for r in rows:
        est = "not found" if r["estimated"] is None else "[" + ", ".join(f"{v:+.3f}" for v in r["estimated"]) + "]"
        err = "" if r["error_m"] is None else f"  error {r['error_m'] * 1000:.1f} mm"
        print(f"{r['name']:<14} {r['status']:<9} estimated {est}  true [" + ", ".join(f"{v:+.3f}" for v in r["true"] or [])
              + f"]{err}")
    print(f"camera {args.camera} at {args.size}x{args.size}; {seen.ms:.1f} ms; drawn in {image}")
    return 0
