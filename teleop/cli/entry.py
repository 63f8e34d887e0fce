"""`teleop` command line: one subcommand per job, each defined next to what it drives.

Every error a user can cause (a `TeleopError`: a flag, a file, a device, the disk)
ends as one line on stderr and exit code 2;
tracebacks are for bugs only. With `--json`, stdout carries the one JSON object
and nothing else, `{"error": ...}` when the command fails, a usage error included
(teleop/cli/json_output.py).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from typing import NoReturn

from teleop.cli import annotate as cli_annotate
from teleop.cli import bench as cli_bench
from teleop.cli import campaign as cli_campaign
from teleop.cli import catalog as cli_catalog
from teleop.cli import devices as cli_devices
from teleop.cli import episodes as cli_episodes
from teleop.cli import eval as cli_eval
from teleop.cli import export as cli_export
from teleop.cli import generate as cli_generate
from teleop.cli import perceive as cli_perceive
from teleop.cli import run as cli_run
from teleop.cli import review as cli_review
from teleop.cli import serve as cli_serve
from scenes.errors import TeleopError, first_line
from teleop.cli.json_output import json_command, print_json
from teleop.cli.signals import terminate_as_interrupt

# One module per command group, in the order `teleop --help` lists them.
MODULES = (cli_catalog, cli_run, cli_bench, cli_episodes, cli_serve, cli_campaign, cli_devices, cli_export, cli_annotate,
           cli_review, cli_generate, cli_eval, cli_perceive)


class Parser(argparse.ArgumentParser):
    """argparse's parser (its subcommands' too); a usage error in a `--json` command line is also
    answered on stdout as `{"error": ...}`, before argparse's usage and exit code 2."""

    json_requested = False  # set by `main` from the command line, before parsing

    def error(self, message: str) -> NoReturn:
        if Parser.json_requested:
            print_json({"error": message})
        super().error(message)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="teleop",
        description="Teleoperate MuJoCo robot arms, record demonstrations, replay them exactly, export datasets.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in MODULES:
        module.add_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    Parser.json_requested = "--json" in argv
    args = parser.parse_args(argv)
    terminate_as_interrupt()  # SIGTERM ends a session the way Ctrl-C does: the episode in progress is kept
    as_json = bool(getattr(args, "json", False))
    try:
        # --json: exactly one object on stdout whatever happens ({"error": ...} when the command printed none)
        with json_command(args.command) if as_json else contextlib.nullcontext():
            return int(args.func(args) or 0)
    except TeleopError as exc:
        print(f"teleop {args.command}: error: {first_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"teleop {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `teleop scenes | head`: the reader left; what it read is all it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
