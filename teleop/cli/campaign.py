"""`teleop campaign FILE`: a collection campaign, many operators at once, each in a session of their own.

Reads the campaign file (teleop/campaign/file.py), serves the lobby on --host/--port and
prints the admin URL and the join URL (and, for a list of operators, each one's invite
link, once). Runs until Ctrl-C, which ends every session (each saves its episode in
progress, marked incomplete). docs/campaigns.md tells the whole story.
"""

from __future__ import annotations

import argparse
import secrets
from pathlib import Path

from teleop.cli.signals import cancel_on_interrupt
from teleop.errors import UsageError

TOKEN_HELP = "8-128 characters from A-Z a-z 0-9 . _ ~ -; default: a random one, printed once"


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser(
        "campaign",
        help="collect demonstrations with many operators at once: a lobby that gives each their own session",
        description="Serve a collection campaign: operators open the join URL, type a name and get a browser "
        "session of their own; the admin URL shows every session live. Ctrl-C ends it (episodes in progress "
        "are saved, marked incomplete); starting it again continues the counts.",
    )
    p.add_argument("file", type=Path, metavar="FILE.toml", help="the campaign file (docs/campaigns.md)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address the lobby and the sessions listen on (default 127.0.0.1; 0.0.0.0 for other machines)")
    p.add_argument("--port", type=int, default=8080, help="the lobby's port (default 8080); sessions get free ports")
    p.add_argument("--token", default=None, metavar="TEXT", help=f"the admin token: {TOKEN_HELP}")
    p.add_argument("--join-token", default=None, metavar="TEXT", help=f"the join URL's token: {TOKEN_HELP}")
    p.add_argument("--ray", default=None, metavar="ADDRESS",
                   help="start sessions as Ray actors on a cluster's nodes (one CPU each): 'auto', HOST:PORT or "
                   "ray://HOST:PORT; the lobby stays here and sends each browser to its node. out/ must be a folder "
                   "every node sees. Needs .[cluster]")
    p.set_defaults(func=cmd_campaign)


def _token(value: str | None, flag: str) -> str:
    from teleop.web.shared.access import TOKEN_PATTERN

    if value is None:
        return secrets.token_urlsafe(18)
    if not TOKEN_PATTERN.fullmatch(value):
        raise UsageError(f"{flag}: a token is 8 to 128 characters from A-Z a-z 0-9 . _ ~ -")
    return value


def cmd_campaign(args: argparse.Namespace) -> int:
    from teleop.campaign.file import load_campaign
    from teleop.campaign.ledger import issue_invites
    from teleop.campaign.lobby import Lobby, start_lobby
    from teleop.web.shared.net import check_port_free, page_url, remote_hint

    admin_token, join_token = _token(args.token, "--token"), _token(args.join_token, "--join-token")
    if admin_token == join_token:
        raise UsageError("--token and --join-token must differ: the join URL must not open the admin page")
    campaign = load_campaign(args.file)
    check_port_free(args.host, args.port)
    campaign.out.mkdir(parents=True, exist_ok=True)
    invites = issue_invites(campaign.out, campaign.operators) if campaign.operators else {}
    lobby = Lobby(campaign, args.host, admin_token, join_token, ray_address=args.ray)
    with cancel_on_interrupt(even_if_ignored=True) as stop:
        server = start_lobby(lobby, args.port)
        base = page_url(args.host, args.port)
        print(f"teleop campaign {campaign.name}: {len(campaign.tasks)} tasks, "
              f"{lobby.wanted_total} successful episodes wanted, into {campaign.out}", flush=True)
        print(f"admin: {base}/admin?token={admin_token}", flush=True)
        if campaign.open:
            print(f"join:  {base}/join?token={join_token}", flush=True)
        for name, token in invites.items():
            print(f"invite for {name}: {base}/join?token={token}", flush=True)
        if campaign.operators and len(invites) < len(campaign.operators):
            print("invites issued before are kept (stored hashed in out/.campaign/invites.json)", flush=True)
        hint = remote_hint(args.host)
        if hint:
            print(hint, flush=True)
        print("Ctrl-C ends the campaign and every session", flush=True)
        try:
            while not stop.wait(0.5):
                pass
        finally:
            server.shutdown()
            lobby.sessions.close()
            server.server_close()
    print(f"teleop campaign {campaign.name}: stopped", flush=True)
    return 0
