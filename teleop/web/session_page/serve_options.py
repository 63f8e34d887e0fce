"""`ServeOptions`: how one session is served to browsers, in one object.

`serve()` and `WebApp` took the same dozen settings one keyword each; they share this
object instead, `teleop serve` builds it from its flags (teleop/cli/serve.py), a campaign's
session process from its spec, and a script through `teleop.serve(session, port=...)`.
What has a life of its own (started devices, a policy, a follower arm, the stop event,
the log) stays an argument of `serve()`: an options object only describes.

Light on purpose: no viser here, so the command line can build and check it before the
browser server loads.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from teleop.errors import UsageError

__all__ = ["DEFAULT_STATUS_PERIOD_S", "ServeOptions", "asks_for_keyboard"]

DEFAULT_STATUS_PERIOD_S = 0.2  # s between status-file writes of a session when its options do not say
XR_PAGE = "teleop.web.xr_page.xr_server:XrServer"  # the XR page's companion (teleop/web/xr_page/), by name


@dataclass(frozen=True)
class ServeOptions:
    """The settings of a served session; each is `teleop serve`'s flag of that name where it has one.

    A bad value raises UsageError (one line; exit 2 through the command line) as the object is made.
    """

    host: str = "127.0.0.1"  # the address to listen on; loopback is this machine only, 0.0.0.0 every interface
    port: int = 8080  # TCP port; 0: the system picks a free one as the server binds (the status file's `port` says which)
    pos_speed: float = 0.15  # m/s: hold-to-move speed of the keyboard, SpaceMouse and the page's keys
    rot_speed: float = 0.8  # rad/s: hold-to-rotate speed of the same
    token: str | None = None  # the secret every browser brings (?token=...); None: TELEOP_TOKEN, else none on loopback, random elsewhere
    no_token: bool = False  # serve a non-loopback host with no token (trusted networks; warns on stderr)
    page_keyboard: bool | None = None  # keys typed in the page drive as the keyboard; None: when a keyboard is among the devices
    policy_device: str = "cpu"  # torch device that loads a policy given as a folder or script (not an already loaded Policy)
    keep_scene: bool = False  # Save, Stop and Discard leave the scene as it is (default: next seed, every episode from its start)
    status_file: Path | None = None  # a JSON status file rewritten while serving (scripts, tests, a campaign's lobby); None: none
    status_period_s: float = DEFAULT_STATUS_PERIOD_S  # s between status-file writes
    status_form: Callable[[dict], str] | None = None  # the status file's text from the status dict (None: the dict as JSON)
    headline: Callable[[], str] | None = None  # a line of markdown under the task, asked at 4 Hz (a campaign's progress)
    draw_unwatched: bool = True  # send scene updates with no browser connected (False saves the CPU then)
    print_token: bool = True  # False: the log shows the page's URL without its token (a campaign's log is a file)
    # Pages served beside the session page on its port, each made from the session's arm count when the server
    # starts: a factory, or its name "module:factory" (imported then: the session page's room imports no other page's).
    # A companion has `key` (its name), `device` (polled with the others), `pages` (path -> HTML), `routes` (path ->
    # websocket handler), `tick(controller, snapshot, device_problems)` run after every control tick on the loop's
    # thread, and `status()` (a dict). Default: the XR page (`/xr`, docs/xr.md).
    companions: tuple[str | Callable[[int], object], ...] = (XR_PAGE,)
    tls_cert: Path | None = None  # PEM certificate: every page and websocket over TLS (https, wss); with tls_key
    tls_key: Path | None = None  # its PEM private key (`teleop serve --https` makes a self-signed pair: teleop/cli/tls_args.py)

    def __post_init__(self) -> None:
        if not isinstance(self.host, str) or not self.host.strip():
            raise UsageError(f"host (--host) {self.host!r}: give an address to listen on, such as 127.0.0.1")
        if isinstance(self.port, bool) or not isinstance(self.port, int) or not 0 <= self.port <= 65535:
            raise UsageError(f"port (--port) {self.port!r}: must be 1..65535 (or 0: the system picks one)")
        for name, flag, unit in (("pos_speed", " (--pos-speed)", "m/s"), ("rot_speed", " (--rot-speed)", "rad/s"),
                                 ("status_period_s", "", "s")):
            if not _positive(getattr(self, name)):
                raise UsageError(f"{name}{flag} {getattr(self, name)!r}: must be a number of {unit} above 0")
        if self.token is not None and self.no_token:
            raise UsageError("--token and --no-token contradict each other: give one")
        if not isinstance(self.policy_device, str) or not self.policy_device:
            raise UsageError(f"policy_device {self.policy_device!r}: a torch device such as cpu, cuda or mps")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise UsageError("--tls-cert and --tls-key go together: give both (or --https for a certificate made here)")
        if self.status_file is not None:
            object.__setattr__(self, "status_file", Path(self.status_file))  # a str from a script is a path too


def asks_for_keyboard(words: list[str]) -> bool:
    """Whether a --device list names the keyboard (then keys typed in the page drive too, started or not)."""
    return any(w.strip().partition(":")[0].lower() == "keyboard" for w in words)


def _positive(value: object) -> bool:
    """A real number above 0 and finite (bool is no speed)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
