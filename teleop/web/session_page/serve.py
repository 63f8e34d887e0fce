"""`serve`: a session in the browser until Ctrl-C, for `teleop serve` and for scripts.

The recorder attached to the session (if any) is switched to the browser's
policy: exact-replay checks run in the background so saving never stalls the
real-time loop, and a write error stops recording while driving goes on.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from devices.base import Device
from devices.registry import SERVE_DEVICES, DeviceOptions, open_devices
from scenes.workers import shielded
from teleop.control.session import Session
from teleop.web.shared.access import resolve_token
from teleop.web.session_page.app import STATUS_PERIOD_S, WebApp
from teleop.web.shared.net import check_port_free, exposure_warning, remote_hint

if TYPE_CHECKING:  # annotations only
    from teleop.control.follower import Follower
    from teleop.learn.policy import Policy

DEFAULT_DEVICES = SERVE_DEVICES  # also teleop serve's --device default


def asks_for_keyboard(words: list[str]) -> bool:
    """Whether a --device list names the keyboard (then keys typed in the page drive too, started or not)."""
    return any(w.strip().partition(":")[0].lower() == "keyboard" for w in words)


def serve(
    session: Session,
    devices: Sequence[str | Device] = DEFAULT_DEVICES,
    host: str = "127.0.0.1",
    port: int = 8080,
    pos_speed: float = 0.15,
    rot_speed: float = 0.8,
    status_file: Path | None = None,
    problems: Sequence[str] = (),
    log: Callable[[str], None] = print,
    policy: "Policy | str | Path | None" = None,
    policy_device: str = "cpu",
    token: str | None = None,
    no_token: bool = False,
    page_keyboard: bool | None = None,
    headline: Callable[[], str] | None = None,
    draw_unwatched: bool = True,
    stop: threading.Event | None = None,
    status_period_s: float = STATUS_PERIOD_S,
    keep_scene: bool = False,
    status_form: Callable[[dict], str] | None = None,
    print_token: bool = True,
    follower: "Follower | None" = None,
) -> int:
    """Serve `session` at http://host:port until Ctrl-C or `stop` is set; returns 0, or 1 if the loop failed.

    devices: spec words ("gizmo", "keyboard", "spacemouse[:N...]", "script:FILE")
    and/or started Device objects; words that cannot start are listed on the page.
    pos_speed / rot_speed: hold-to-move speeds (m/s, rad/s) for keyboard and SpaceMouse.
    An episode in progress at the end is saved, marked incomplete; a Ctrl-C meanwhile waits for it.
    stop: a cancellation token (`teleop serve` sets it on Ctrl-C and SIGTERM); a script may
    rely on the KeyboardInterrupt of its own Ctrl-C instead.
    policy: a Policy, a LeRobot pretrained-model folder or `script:FILE`; it drives until
    the operator touches a device, and gets control back by the key `p` or the panel's
    button (teleop.learn.takeover). Recorded episodes then say who drove each step.
    token: the secret every browser must bring (`?token=...` in the printed URL); default
    TELEOP_TOKEN, else none on loopback and a random one on any other host.
    no_token: serve a non-loopback host with no token (trusted networks; warns on stderr).
    page_keyboard: keys typed in the page drive as the keyboard does (default: when a keyboard
    is among `devices`, started or not).
    headline: a line of markdown the panel shows under the task, asked a few times a second
    (a campaign's progress: teleop/campaign/progress.py).
    draw_unwatched: send scene updates with no browser connected (False: none then, saving the CPU).
    port: 0 binds a port the system picks (the status file's `port` says which).
    status_form: what the status file holds, made from the status dict (default: that dict as JSON).
    print_token: False logs the page's URL without its token (a campaign's session, whose log is a file:
    the lobby hands the URL to the operator instead).
    keep_scene: Save, Stop and Discard leave the scene as it is and the next episode starts from there
    (default: they move to the next seed, and every episode starts from its seed's initial state).
    follower: a real arm already following `session` (teleop.control.follower); its state is on the page
    and in the status, and it is closed (torque off) when serving ends, however it ends.
    """
    token = resolve_token(host, token, no_token)  # a bad combination fails before anything starts
    if port != 0:
        check_port_free(host, port)
    session.fresh_episodes = not keep_scene
    words = [d for d in devices if isinstance(d, str)]
    started = [d for d in devices if not isinstance(d, str)]
    if page_keyboard is None:
        page_keyboard = asks_for_keyboard(words) or any(d.kind == "keyboard" for d in started)
    problems = list(problems)
    if words:
        options = DeviceOptions(pos_speed=pos_speed, rot_speed=rot_speed, n_arms=session.controller.n_arms)
        opened, failed = open_devices(",".join(words), options, require_any=False, require_known=True)
        started += opened
        problems += failed
    recorder = session.recorder
    if recorder is not None:
        recorder.on_error = "stop"
        if recorder.verify == "sync":
            recorder.verify = "background"
    takeover = None
    try:
        if policy is not None:
            takeover = _takeover(session, policy, policy_device)
        app = WebApp(session, started, problems, host=host, port=port, status_file=status_file,
                     pos_speed=pos_speed, rot_speed=rot_speed, log=log, takeover=takeover, token=token,
                     page_keyboard=page_keyboard, headline=headline, draw_unwatched=draw_unwatched,
                     status_period_s=status_period_s, status_form=status_form)
    except BaseException:
        for d in started:
            d.close()
        if takeover is not None:
            takeover.close()
        raise
    app.follower = follower
    warning = exposure_warning(host, port) if token is None else None
    if warning:
        print(warning, file=sys.stderr)
    app.start()
    where = f", recording into {recorder.directory}" if recorder is not None else " (not recording: add --record DIR)"
    log(f"teleop serve: {session.robot.name} on {session.scene_name}{where}")
    if takeover is not None:
        log(f"policy {takeover.policy.name} drives; touch any device to take over, press p (or the panel's button) to hand back")
    log(f"open {app.page_url if print_token else app.url} in a browser (Ctrl-C to stop)")
    hint = remote_hint(host)
    if hint:
        log(hint)

    try:
        while not app.wait(0.2):
            if stop is not None and stop.is_set():
                break
        if app.sim.error:
            print(f"teleop serve: control loop stopped: {app.sim.error}", file=sys.stderr)
    except KeyboardInterrupt:
        pass
    finally:
        saved, _ = shielded(lambda: _close(app, takeover))  # a second Ctrl-C must not cut a file short
        if follower is not None:
            shielded(follower.close)  # stop sending, torque off
    for path in saved:
        log(f"saved {path} (incomplete: stopped mid-episode)")
    snap = app.sim.snapshot
    log(f"teleop serve: stopped; episodes saved {snap.episodes_saved}, discarded {snap.episodes_discarded}")
    return 1 if app.sim.error else 0


def _takeover(session: Session, policy, device: str):
    """The policy side, imported only when a policy drives (gymnasium, the export's renderer, LeRobot)."""
    from teleop.learn.takeover import Takeover, load_policy

    if not hasattr(policy, "select_action"):
        policy = load_policy(policy, device)
    takeover = Takeover.for_session(session, policy)
    recorder = session.recorder
    if recorder is not None:  # episodes say a policy drove, which one, and (per step) when the operator did
        recorder.source = "policy"
        recorder.provenance["policy"] = policy.name
    return takeover


def _close(app: WebApp, takeover) -> list[Path]:
    """Stop serving and save an episode in progress (marked incomplete); its files."""
    try:
        return app.close()
    finally:
        if takeover is not None:
            takeover.close()
