"""`teleop devices [--json]`: list the input devices this machine offers, and why not for the rest."""

from __future__ import annotations

import argparse

from teleop.cli.json_output import print_json


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser(
        "devices",
        help="list input devices (keyboard, SpaceMouse, gizmo, script) and why any is unavailable",
        description="List every input device teleop can see or not see, and why; then the keyboard "
        "bindings and the SpaceMouse setup.",
    )
    p.add_argument("--json", action="store_true", help='print one JSON object {"devices": [{name, kind, available, reason, ...}], '
                   '"serial": [{port, by_id, servos: [{id, model, ...}], fits, ...}]}')
    p.add_argument("--port", action="append", default=[], metavar="PATH",
                   help="also probe this serial device for servos (repeatable); USB serial adapters are probed anyway")
    p.set_defaults(func=run_devices)


def help_text() -> str:
    """Keyboard bindings and SpaceMouse mapping/setup, as printed under the device table."""
    from devices.gamepad import MAPPING
    from devices.keyboard import bindings_table
    from devices.spacemouse import RIGHT_BUTTON_ACTIONS, UDEV_HOWTO
    from devices.spacemouse_protocol import STANCE_HELP

    stances = "\n".join(f"  {name:7} {text}" for name, text in STANCE_HELP.items())
    return (
        "Keyboard (hold a key to move at --pos-speed / --rot-speed; world frame: x away from the base, z up):\n"
        f"{bindings_table()}\n"
        "  Keys are read from every window of the display; with Ctrl, Alt or Super held they are ignored.\n\n"
        "SpaceMouse (--device spacemouse[:N][:behind|facing][:toggle|hold][:right=ACTION]):\n"
        f"{stances}\n"
        "  left button: gripper (toggle, or hold = closed while held); "
        f"right button: {'|'.join(RIGHT_BUTTON_ACTIONS)} (default reset)\n"
        "  Two SpaceMice drive arms 0 and 1 of a bimanual scene.\n"
        "  Linux access without root (then replug):\n"
        + "\n".join("    " + line for line in UDEV_HOWTO.splitlines())
        + "\n  If spacenavd holds it: sudo systemctl stop spacenavd\n\n"
        "In the browser (teleop serve; work when the server runs on another machine):\n"
        "  keys typed in the page: the keyboard bindings above\n"
        "  gamepad (Gamepad API, standard mapping; PlayStation: A = cross, B = circle, LB/RB = L1/R1, Start = Options):\n"
        + "\n".join(f"    {control:12} {action}" for control, action in MAPPING)
        + "\n  phone: open the page's /phone address on the phone; hold the big button and move the phone\n"
        "  webhid: 'Connect SpaceMouse' in the panel (Chrome, Edge) reads a SpaceMouse plugged into the browser's machine"
    )


def serial_text(ports: list, note: str | None) -> str:
    """The serial-port table of `teleop devices`: each port, its by-id name and what answered on it."""
    if not ports:
        lines = ["Serial ports: none (a leader arm's USB adapter shows up as /dev/ttyACM* or /dev/ttyUSB*; name others with --port)"]
    else:
        width = max(len("SERIAL PORT"), *(len(p.port) for p in ports))
        lines = [f"{'SERIAL PORT'.ljust(width)}  SERVOS"]
        for p in ports:
            lines.append(f"{p.port.ljust(width)}  {p.summary()}")
            if p.by_id:
                lines.append(f"{' ' * width}  ({p.by_id})")
    if note:
        lines.append(note)
    return "\n".join(lines)


def run_devices(args: argparse.Namespace) -> int:
    import os

    from devices.discovery import discover
    from devices.serial_ports import serial_ports
    from teleop.errors import UsageError

    for path in args.port:
        if not os.path.exists(path):
            raise UsageError(f"--port {path}: no such device")
    rows = discover()
    ports, note = serial_ports(args.port)
    if args.json:
        out = {"devices": [r.to_dict() for r in rows], "serial": [p.to_dict() for p in ports]}
        if note:
            out["serial_note"] = note
        print_json(out, indent=2)
        return 0
    width = max(len(r.name) for r in rows)
    print(f"{'NAME'.ljust(width)}  {'KIND':10}  {'AVAILABLE':9}  REASON")
    for r in rows:
        print(f"{r.name.ljust(width)}  {r.kind:10}  {'yes' if r.available else 'no':9}  {r.reason}")
    print()
    print(serial_text(ports, note))
    print()
    print(help_text())
    return 0
