"""Where the server listens, and the checks that keep that explicit.

viser would listen on every interface and quietly move to the next port if
the one asked for is taken; an operator then opens the wrong page or exposes
a robot to the network without meaning to. So the host is always passed on,
a taken port is an error, and any host other than loopback gets a warning.
"""

from __future__ import annotations

import errno
import ipaddress
import socket

from teleop.errors import UsageError

def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposure_warning(host: str, port: int) -> str | None:
    """The warning to print when the session is reachable from other machines."""
    if is_loopback(host):
        return None
    return (
        f"warning: listening on {host}:{port}: anyone who can reach this port can drive the robot session "
        "and start, save or discard recordings (there is no login); use --host 127.0.0.1 to keep it local"
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
                    raise UsageError(f"port {port} is already in use on {host}; stop what uses it or pass --port N") from None
                if exc.errno in (errno.EADDRNOTAVAIL, errno.EAFNOSUPPORT):
                    raise UsageError(f"--host {host}: not an address of this machine") from None
                if exc.errno == errno.EACCES:
                    raise UsageError(f"port {port}: permission denied (ports below 1024 need privileges)") from None
                raise UsageError(f"cannot listen on {host}:{port}: {exc.strerror}") from None


def page_url(host: str, port: int) -> str:
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
    if ":" in shown:
        shown = f"[{shown}]"
    return f"http://{shown}:{port}"
