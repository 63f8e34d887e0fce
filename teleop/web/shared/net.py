"""Where a browser server listens, and the checks that keep that explicit.

viser would listen on every interface and quietly move to the next port if
the one asked for is taken; an operator then opens the wrong page or exposes
a robot to the network without meaning to. So the host is always passed on,
a taken port is an error, and a host other than loopback needs a token
(teleop.web.shared.access) or, with --no-token, gets a warning. Both servers (the
teleop session and the replay viewer) check here.
"""

from __future__ import annotations

import errno
import ipaddress
import socket

from teleop.errors import UsageError

__all__ = ["check_port_free", "exposure_warning", "is_loopback", "page_url", "remote_hint"]

SESSION_REACH = "drive the robot session and start, save or discard recordings"


def is_loopback(host: str) -> bool:
    """Whether `host` is reachable from this machine only (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposure_warning(host: str, port: int, reach: str = SESSION_REACH) -> str | None:
    """The one-line warning to print when a server is reachable from other machines without a token;
    `reach` says what anyone could then do there."""
    if is_loopback(host):
        return None
    return (
        f"warning: --no-token: listening on {host}:{port} without a token: anyone who can reach this port can "
        f"{reach}; drop --no-token, or use --host 127.0.0.1"
    )


def check_port_free(host: str, port: int) -> None:
    """Raise UsageError naming the port if something already listens there (or the host is wrong)."""
    if not 0 < port <= 65535:
        raise UsageError(f"--port {port}: must be 1..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise UsageError(f"--host {host}: cannot listen there ({exc.strerror})") from None
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT is not "in use"
            try:
                probe.bind(addr)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    raise UsageError(
                        f"port {port} is already in use on {host}; stop what uses it or pass --port N") from None
                if exc.errno in (errno.EADDRNOTAVAIL, errno.EAFNOSUPPORT):
                    raise UsageError(f"--host {host}: not an address of this machine") from None
                if exc.errno == errno.EACCES:
                    raise UsageError(f"port {port}: permission denied (ports below 1024 need privileges)") from None
                raise UsageError(f"cannot listen on {host}:{port}: {exc.strerror}") from None


def page_url(host: str, port: int) -> str:
    """The address a browser on this machine opens: a wildcard host becomes its loopback
    (0.0.0.0 -> 127.0.0.1, :: -> [::1]), and an IPv6 host goes in brackets."""
    shown = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
    if ":" in shown:
        shown = f"[{shown}]"
    return f"http://{shown}:{port}"


def remote_hint(host: str) -> str | None:
    """For a wildcard host, the line that tells how to open the page from another machine."""
    if host not in ("", "0.0.0.0", "::"):
        return None
    local = "[::1]" if host == "::" else "127.0.0.1"
    return f"  (from another machine: this machine's name or address in place of {local})"
