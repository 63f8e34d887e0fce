"""`serve`: a session in the browser until Ctrl-C, for `teleop serve` and for scripts.

The recorder attached to the session (if any) is switched to the browser's
policy: exact-replay checks run in the background so saving never stalls the
real-time loop, and a write error stops recording while driving goes on.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from devices.base import Device
from devices.registry import SERVE_DEVICES, DeviceOptions, open_devices
from scenes.workers import shielded
from teleop.control.session import Session
from teleop.web.shared.access import resolve_token
from teleop.web.session_page.app import WebApp
from teleop.web.session_page.serve_options import ServeOptions, asks_for_keyboard
from teleop.web.shared.net import check_port_free, exposure_warning, remote_hint

if TYPE_CHECKING:  # annotations only
    from teleop.control.follower import Follower
    from teleop.learn.policy import Policy

DEFAULT_DEVICES = SERVE_DEVICES  # also teleop serve's --device default


def serve(
    session: Session,
    options: ServeOptions | None = None,
    *,
    devices: Sequence[str | Device] = DEFAULT_DEVICES,
    problems: Sequence[str] = (),
    policy: "Policy | str | Path | None" = None,
    follower: "Follower | None" = None,
    stop: threading.Event | None = None,
    log: Callable[[str], None] = print,
) -> int:
    """Serve `session` at http://host:port until Ctrl-C or `stop` is set; returns 0, or 1 if the loop failed.

    options: how it is served (host, port, speeds, token, status file, ...: ServeOptions, default
    ServeOptions()). The rest are things with a life of their own:
    devices: spec words ("gizmo", "keyboard", "spacemouse[:N...]", "script:FILE")
    and/or started Device objects; words that cannot start are listed on the page, as are `problems`
    (devices the caller could not start). Every device is closed when serving ends.
    An episode in progress at the end is saved, marked incomplete; a Ctrl-C meanwhile waits for it.
    policy: a Policy, a LeRobot pretrained-model folder or `script:FILE` (loaded on options.policy_device);
    it drives until the operator touches a device, and gets control back by the key `p` or the panel's
    button (teleop.learn.takeover). Recorded episodes then say who drove each step.
    follower: a real arm already following `session` (teleop.control.follower); its state is on the page
    and in the status, and it is closed (torque off) when serving ends, however it ends.
    stop: a cancellation token (`teleop serve` sets it on Ctrl-C and SIGTERM); a script may
    rely on the KeyboardInterrupt of its own Ctrl-C instead.
    log: where the lines for the operator go (the URL to open, saved files).
    """
    options = ServeOptions() if options is None else options
    if not isinstance(options, ServeOptions):  # serve(session, ["gizmo"]) as before the options object
        raise TypeError(f"serve(): options is a ServeOptions, not {type(options).__name__} (devices go by devices=...)")
    host, port = options.host, options.port
    token = resolve_token(host, options.token, options.no_token)  # a bad combination fails before anything starts
    if port != 0:
        check_port_free(host, port)
    session.fresh_episodes = not options.keep_scene
    words = [d for d in devices if isinstance(d, str)]
    started = [d for d in devices if not isinstance(d, str)]
    page_keyboard = options.page_keyboard
    if page_keyboard is None:
        page_keyboard = asks_for_keyboard(words) or any(d.kind == "keyboard" for d in started)
    options = replace(options, token=token, page_keyboard=page_keyboard)  # what WebApp serves: resolved
    problems = list(problems)
    if words:
        device_options = DeviceOptions(pos_speed=options.pos_speed, rot_speed=options.rot_speed, n_arms=session.controller.n_arms)
        opened, failed = open_devices(",".join(words), device_options, require_any=False, require_known=True)
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
            takeover = _takeover(session, policy, options.policy_device)
        app = WebApp(session, started, problems, options, takeover=takeover, log=log)
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
    log(f"open {app.page_url if options.print_token else app.url} in a browser (Ctrl-C to stop)")
    for path, url in app.companion_urls.items():
        log(f"XR headset: open {url if options.print_token else app.url + path} in the headset's browser")
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
