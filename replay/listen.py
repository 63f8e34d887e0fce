"""Where a browser server listens, checked before viser gets the chance to improvise.

viser would quietly move to the next port when the one asked for is taken, so an
operator opens the wrong page. Both servers (the teleop session and the replay
viewer) check here first; it sits downstream so that both may import it.
"""

from __future__ import annotations

import errno
import ipaddress
import socket

from scenes.errors import TeleopError


class ListenError(TeleopError, ValueError):
    """The host or port cannot be listened on; the message is one line naming which."""


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_port_free(host: str, port: int) -> None:
    """Raise ListenError naming the port if something already listens there (or the host is wrong)."""
    if not 0 < port <= 65535:
        raise ListenError(f"--port {port}: must be 1..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise ListenError(f"--host {host}: cannot listen there ({exc.strerror})") from None
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT is not "in use"
            try:
                probe.bind(addr)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    raise ListenError(f"port {port} is already in use on {host}; stop what uses it or pass --port N") from None
                if exc.errno in (errno.EADDRNOTAVAIL, errno.EAFNOSUPPORT):
                    raise ListenError(f"--host {host}: not an address of this machine") from None
                if exc.errno == errno.EACCES:
                    raise ListenError(f"port {port}: permission denied (ports below 1024 need privileges)") from None
                raise ListenError(f"cannot listen on {host}:{port}: {exc.strerror}") from None
