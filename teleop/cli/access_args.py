"""The listening and access flags of every command that serves a page (`serve`, `replay --serve`, `review`).

What they mean at run time is teleop.web.shared.access's (`resolve_token`, the Gate); here they are declared once.
"""

from __future__ import annotations

import argparse


def add_access_args(p: argparse.ArgumentParser, host: str = "address to listen on", port: str = "port to listen on",
                    when: str = "") -> None:
    """--host, --port, --token and --no-token; `host` and `port` name what they set, `when` prefixes the token
    flags' help (e.g. "with --serve: ")."""
    p.add_argument("--host", default="127.0.0.1", help=f"{host} (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8080, help=f"{port} (default 8080)")
    p.add_argument("--token", default=None, metavar="TEXT",
                   help=f"{when}the secret a browser must bring (the printed URL carries it as ?token=...); default: "
                        "$TELEOP_TOKEN, else a random one when --host is not loopback (loopback needs none)")
    p.add_argument("--no-token", action="store_true",
                   help=f"{when}serve a non-loopback --host with no token (trusted networks only; prints a warning)")
