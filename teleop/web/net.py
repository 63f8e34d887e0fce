"""Where the server listens, and the checks that keep that explicit.

viser would listen on every interface and quietly move to the next port if
the one asked for is taken; an operator then opens the wrong page or exposes
a robot to the network without meaning to. So the host is always passed on,
a taken port is an error, and a host other than loopback needs a token
(teleop.web.access) or, with --no-token, gets a warning.
"""

from __future__ import annotations

from replay import listen
from replay.listen import is_loopback
from teleop.errors import UsageError

__all__ = ["check_port_free", "exposure_warning", "is_loopback", "page_url"]

def exposure_warning(host: str, port: int) -> str | None:
    """The warning to print when the session is reachable from other machines without a token."""
    if is_loopback(host):
        return None
    return (
        f"warning: --no-token: listening on {host}:{port} without a token: anyone who can reach this port can "
        "drive the robot session and start, save or discard recordings; drop --no-token, or use --host 127.0.0.1"
    )


def check_port_free(host: str, port: int) -> None:
    """Raise UsageError naming the port if something already listens there (or the host is wrong)."""
    try:
        listen.check_port_free(host, port)
    except listen.ListenError as exc:
        raise UsageError(str(exc)) from None


def page_url(host: str, port: int) -> str:
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
    if ":" in shown:
        shown = f"[{shown}]"
    return f"http://{shown}:{port}"
