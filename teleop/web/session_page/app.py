"""One served teleop session: the viser server and the threads around one Session.

    control loop (SimThread)  --snapshots-->  drawing (SceneDrawer, <= 60 Hz, cued by each tick,
          |                                            in viser's event loop)
          ^  polls devices                    camera picture (CameraFeed, a few Hz)
          |                                   panel text (Panel, 4 Hz) + status file
    gizmo / panel / keyboard / SpaceMouse / keys in the page (input channel)

Browsers only ever talk to viser and to the page's input channel on the same
port, both behind the session token (access); their callbacks only write into
device mailboxes and key states. So any number of browsers can watch, and one
closing mid-episode changes nothing for the recording. Saved episodes are checked for exact
replay on a worker thread, so a save never stalls the real-time loop.
"""

from __future__ import annotations

import importlib
import json
import os
import ssl
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import viser

from devices.base import SpeedControlled
from devices.keyboard import KeyboardDevice
from replay import VerifyResult
from teleop.errors import UsageError
from teleop.control.session import Session
from teleop.web.shared.access import Gate, url_with_token
from teleop.web.session_page.camera_view import IMAGE_SIZE, CameraFeed
from teleop.web.session_page.drawing import SceneDrawer
from teleop.web.shared.input_channel import PATH as INPUT_PATH
from teleop.web.shared.input_channel import InputChannel, channel_script
from teleop.web.shared.net import check_port_free, page_url
from teleop.web.session_page.page_devices import PageInputs
from teleop.web.session_page.page_keyboard import PageKeyboardDevice, PageKeys
from teleop.web.session_page.panel import Panel, PanelDevice
from teleop.web.session_page.sim_thread import SimThread, Snapshot
from teleop.web.session_page.serve_options import ServeOptions
from teleop.web.shared.view_quality import SoftwareViews, head_script
from teleop.web.viser_internals.guarded_start import start_guarded
from teleop.web.viser_internals.page_script import run_javascript

if TYPE_CHECKING:  # annotations only: the policy side (gymnasium, export) loads only with --policy
    from teleop.learn.takeover import Takeover

PHONE_PATH = "/phone"  # the phone page (teleop/web/session_page/phone.html), served beside viser's


def make_companion(make, n_arms: int):
    """A companion page (ServeOptions.companions) for a session of `n_arms` arms, from its factory or its name."""
    if isinstance(make, str):
        module, _, name = make.partition(":")
        make = getattr(importlib.import_module(module), name)
    return make(n_arms)


class WebApp:
    """Serves `session` to browsers on host:port until `close()`."""

    def __init__(
        self,
        session: Session,
        devices: list,
        device_problems: list[str],
        options: ServeOptions | None = None,
        *,
        camera: bool = True,
        takeover: "Takeover | None" = None,
        log: Callable[[str], None] = print,
    ) -> None:
        """`options` as serve() resolved them: its token is the one required (None: open), page_keyboard
        None is no; camera False: no camera picture (tests, benches); takeover: a policy that drives."""
        options = ServeOptions() if options is None else options
        self.options = options
        host, port, token = options.host, options.port, options.token
        pos_speed, rot_speed = options.pos_speed, options.rot_speed
        self.session = session
        self.takeover = takeover  # a policy driving until the operator touches a device
        self.follower = None  # a real arm mirroring the simulated one (teleop.control.follower.Follower), set by serve()
        self.headline = options.headline  # a line of markdown shown under the task (a campaign's progress), asked at 4 Hz
        self.devices = list(devices)
        self.device_problems = list(device_problems)
        self.host, self.port = host, port
        self.status_file = options.status_file
        self.log = log
        self.camera_size = IMAGE_SIZE
        self.last_saved: Path | None = None
        self._messages: list[str] = []
        self._status_due = 0.0
        self.status_period_s = options.status_period_s  # s between status-file writes
        self._closed = False
        self.gate = Gate.for_server(host, port, token)  # token None: open (loopback, or --no-token)
        self.token = token
        self.status_form = options.status_form  # what the status file holds, made from status() (a campaign's typed status)
        self.has_phone_page = False

        if session.recorder is not None:
            session.recorder.on_verified = self._on_verified
        # Keys typed in the page: into this machine's keyboard device when one runs, else a device of their own.
        self.input = InputChannel()
        self.page_keys: PageKeys | None = None
        if options.page_keyboard:
            keyboard = next((d for d in self.devices if isinstance(d, KeyboardDevice)), None)
            if keyboard is None:
                keyboard = PageKeyboardDevice(pos_speed=pos_speed, rot_speed=rot_speed, n_arms=session.controller.n_arms)
                keyboard.start()
                self.devices.append(keyboard)
            self.page_keys = PageKeys(keyboard)
        # Gamepads, the phone page and WebHID SpaceMice: devices fed by pages over the same channel.
        self.page_inputs = PageInputs(self.page_keys, self.devices)
        self.input.listener = self.page_inputs  # every page talks: at least to say how it draws
        pages = {PHONE_PATH: PageInputs.phone_page()} if self.page_inputs.phone is not None else {}
        self.has_phone_page = bool(pages)
        # Companion pages on the same port (the XR page, ServeOptions.companions): their devices, pages and websockets.
        self.companions = [make_companion(make, session.controller.n_arms) for make in options.companions]
        routes = {INPUT_PATH: self.input.handle}
        for companion in self.companions:
            companion.device.start()
            self.devices.append(companion.device)
            pages = {**pages, **companion.pages}
            routes.update(companion.routes)
        if port != 0:  # port 0: the system picks a free one as viser binds (a campaign's sessions: no race)
            check_port_free(host, port)
        tls = None
        if options.tls_cert is not None:  # every page and websocket over TLS (teleop serve --https / --tls-cert)
            tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            try:
                tls.load_cert_chain(options.tls_cert, options.tls_key)
            except (OSError, ssl.SSLError) as exc:
                raise UsageError(f"--tls-cert {options.tls_cert} / --tls-key {options.tls_key}: cannot load them ({exc})") from None
        self.server = start_guarded(lambda: viser.ViserServer(host=host, port=port, label="teleop", verbose=False),
                                    lambda server: server.stop(), self.gate, routes, pages,
                                    head=head_script(), tls=tls)
        self.software_views = SoftwareViews(self.server)  # viser clients drawing in software, given the cheap view
        self.page_inputs.on_view = self.software_views.reported
        if port == 0:
            self.port = port = self.gate.port = self.server.get_port()
        if self.server.get_port() != port:  # someone took it between our check and viser's bind
            self.server.stop()
            raise UsageError(f"port {port} is already in use on {host}; stop what uses it or pass --port N")
        self.url = page_url(host, port)
        if tls is not None:
            self.url = "https://" + self.url.removeprefix("http://")
        self.page_url = url_with_token(self.url, token)  # what to open: with ?token=... when one is needed
        # the phone page's address, when a phone device runs (with its token: printed, never written to a file)
        self.phone_url: str | None = url_with_token(self.url + PHONE_PATH, token) if self.has_phone_page else None
        # each companion page's address (with its token: printed and shown on the panel, never written to a file)
        self.companion_urls = {path: url_with_token(self.url + path, token) for c in self.companions for path in c.pages}
        self.server.gui.configure_theme(control_width="large", show_logo=False, show_share_button=False)
        self.server.gui.main_panel.dock_right()

        self.gizmo = next((d for d in self.devices if d.kind == "gizmo"), None)
        self.panel_device = PanelDevice()
        self.sim = SimThread(session, [*self.devices, self.panel_device], log=log,
                             steer=takeover.steer if takeover is not None else None)
        self.sim.on_saved = self._on_saved
        self.sim.tick_hooks.extend(c.tick for c in self.companions)
        self.drawer = SceneDrawer(self.server, self.sim, self.gizmo)
        self.drawer.only_watched = not options.draw_unwatched  # a campaign's sessions draw only for a browser
        self.panel = Panel(self.server, self, tuple(session.scene.cameras), pos_speed, rot_speed)
        self.camera: CameraFeed | None = None
        if camera and session.scene.cameras:
            self.camera = CameraFeed(
                lambda: self.sim.snapshot, tuple(session.scene.cameras), lambda: self.panel.camera_name, self.panel.show_image,
                self._camera_failed, wanted=lambda: bool(self.server.get_clients()), notice=self.panel.camera_note,
            )
        elif camera:
            self.panel.camera_failed("this scene has no cameras")
        self.server.on_client_connect(self._client_connected)
        self.server.on_client_disconnect(self._client_disconnected)

    # -- life cycle ------------------------------------------------------
    def start(self) -> None:
        if self.camera is not None:
            # The GL context and model upload hold the GIL for ~0.1 s: do it before the loop runs.
            self.camera.start()
            self.camera.ready.wait(60.0)
        self.sim.start()
        self.drawer.start()
        self.panel.start()

    def close(self) -> list[Path]:
        """Stop everything; an episode in progress is saved, marked incomplete. Returns its files."""
        if self._closed:
            return []
        self._closed = True
        self.panel.stop()
        if self.camera is not None:
            self.camera.stop()
        self.drawer.stop()
        if self.page_keys is not None:
            self.page_keys.release_all()
        self.sim.stop()
        recorder = self.session.recorder
        before = len(recorder.paths) if recorder is not None else 0
        try:
            self.session.close()
        finally:
            for device in self.devices:
                try:
                    device.close()
                except Exception:  # noqa: BLE001 - closing anyway
                    pass
            self.write_status()
            self.server.stop()
        return list(recorder.paths[before:]) if recorder is not None else []

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the control loop ends (an error) or `timeout`; True if it ended."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.sim.alive:
            if deadline is not None and time.monotonic() >= deadline:
                return False
            time.sleep(0.2)
        return True

    # -- hooks from the threads ------------------------------------------
    def _client_connected(self, client: viser.ClientHandle) -> None:
        # The page's input script, with this page's client id; viser has no public call for this.
        source = self.page_keys.script(client.client_id) if self.page_keys is not None else \
            channel_script(client.client_id, keys=[])
        if self.page_inputs.any_device:
            source += self.page_inputs.script()
        run_javascript(client, source)
        self._clients_changed()

    def _client_disconnected(self, client: viser.ClientHandle) -> None:
        if self.page_keys is not None:
            self.page_keys.release_client(client.client_id)
        self.software_views.forget(client.client_id)
        self._clients_changed()

    def _clients_changed(self) -> None:
        count = len(self.server.get_clients())
        if self.gizmo is not None:
            self.gizmo.clients = count
            if count == 0:
                self.gizmo.release()

    def _camera_failed(self, message: str) -> None:
        self.note(message)
        self.panel.camera_failed(message)

    def set_speeds(self, pos_speed: float | None = None, rot_speed: float | None = None) -> None:
        """Panel sliders: hold-to-move speeds of every keyboard and SpaceMouse."""
        for device in self.devices:
            if not isinstance(device, SpeedControlled):
                continue
            if pos_speed is not None:
                device.pos_speed = pos_speed
            if rot_speed is not None:
                device.rot_speed = rot_speed

    def note(self, message: str) -> None:
        if not self._messages or self._messages[-1] != message:
            self._messages.append(message)
            del self._messages[:-20]

    def notes(self) -> list[str]:
        return [*self.session.stats.messages[-5:], *self._messages[-5:]]

    @property
    def verified(self) -> dict[str, bool | None]:
        """Episode file -> replays bit for bit (None: still checking)."""
        recorder = self.session.recorder
        return dict(recorder.verified) if recorder is not None else {}

    def _on_saved(self, paths: list[Path]) -> None:
        """Called in the control loop when episodes were saved (the recorder checks them in the background)."""
        if not paths:
            return
        self.last_saved = Path(paths[0])
        self.log(f"saved {', '.join(str(p) for p in paths)}")

    def _on_verified(self, path: Path, result: VerifyResult | None) -> None:
        if result is None:
            self.note(f"{path.name}: the replay check could not run")
        elif not result.bit_exact:
            self.note(f"{path.name} did not replay exactly (first difference at step {result.first_divergence_step})")

    def last_saved_line(self) -> str:
        """The newest saved episode and whether it replays exactly, for the panel."""
        if self.last_saved is None:
            return ""
        state = self.verified.get(str(self.last_saved), "unchecked")
        word = {None: "checking exact replay…", True: "replays exactly ✓", False: "**does not replay exactly**"}.get(state, "")
        return f"Last: `{self.last_saved.name}` {word}".rstrip()

    # -- status (panel figures; a JSON file for scripts and tests) ---------
    def status(self) -> dict:
        snap: Snapshot = self.sim.snapshot
        session = self.session
        model = snap.model
        objects = {}
        for j in range(model.njnt):
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                adr = model.jnt_qposadr[j]
                objects[model.body(model.jnt_bodyid[j]).name] = [round(float(v), 6) for v in snap.qpos[adr:adr + 3]]
        return {
            "url": self.url,
            "port": self.port,
            "token_required": self.gate.token is not None,
            "pid": os.getpid(),
            "wall_time": time.time(),
            "scene": session.scene_name,
            "robot": session.robot.name,
            "seed": snap.seed,
            "fresh_episodes": session.fresh_episodes,  # Save / Stop / Discard move to the next seed (off: --keep-scene)
            "device_restarts": self.sim.device_restarts,  # new scenes on which Restartable devices began again
            "variation": session.scene.variation or None,  # the physics drawn for this seed (--vary), else null
            "control_hz": session.control_hz,
            "tick": snap.tick,
            "sim_time": round(snap.sim_time, 6),
            "loop_hz": round(self.sim.loop_hz(), 2),
            "tick_ms": round(self.sim.compute_ms(), 3),
            "headroom_x": round(self.sim.headroom(), 1),
            "realtime_factor": round(self.sim.realtime_factor(), 4),
            "slips": self.sim.slips,
            "max_late_ms": round(self.sim.max_late_s * 1000.0, 1),
            "recording": snap.recording,
            "episode_steps": snap.episode_steps,
            "episodes_saved": snap.episodes_saved,
            "episodes_discarded": snap.episodes_discarded,
            "saved_files": [str(p) for p in session.recorder.paths] if session.recorder is not None else [],
            "record_dir": str(session.recorder.directory) if session.recorder is not None else None,
            "verified": self.verified,
            "recording_error": snap.recording_error,
            "success": snap.success,
            "ee_pos": [[round(float(v), 6) for v in p] for p, _ in snap.ee],
            "target_pos": [[round(float(v), 6) for v in p] for p, _ in snap.targets],
            "target_quat": [[round(float(v), 6) for v in q] for _, q in snap.targets],
            "gripper_open": list(snap.gripper_open),
            "ik_error_mm": [round(float(e) * 1000, 3) for e in snap.tracking_error_m],
            "ik_failures": snap.ik_failures,
            "objects": objects,
            "clients": len(self.server.get_clients()),
            "software_views": len(self.software_views),
            "web_update_ms": round(self.drawer.update_ms(), 3),
            "web_updates": self.drawer.updates,
            "latency_ms": None if self.drawer.latency_ms is None else round(self.drawer.latency_ms, 2),
            "key_to_tick_ms": [round(v, 2) for v in list(self.sim.tick_latency_ms)[-50:]],  # the newest, oldest first
            "gizmo_drags": self.gizmo.drags if self.gizmo is not None else 0,
            "camera_frames": self.camera.frames if self.camera is not None else 0,
            "camera_still": self.camera.still if self.camera is not None else 0,  # pictures not redrawn: nothing moved
            "camera_crowded": self.camera.crowded if self.camera is not None else False,  # one picture a second
            "camera_problem": self.camera.problem if self.camera is not None else None,
            "devices": {d.name: self.sim.device_problems.get(d.name) or d.status() for d in self.devices},
            "devices_not_started": list(self.device_problems),
            "input_dropped": self.input.dropped,
            "input": self.input.status(),
            "page_keyboard": self.page_keys.state() if self.page_keys is not None else None,
            "phone_url": self.url + PHONE_PATH if self.phone_url is not None else None,  # no token in a file
            **{c.key: c.status() for c in self.companions},  # "xr": the XR page's channel and safety counts
            "driver": self.takeover.driver if self.takeover is not None else "operator",
            "policy": self.takeover.status() if self.takeover is not None else None,
            "follower": self.follower.status() if self.follower is not None else None,  # --follower: state, gap, sends
            "notes": self.notes(),
            "headline": self.headline() if self.headline is not None else None,
            "error": self.sim.error,
        }

    def tick_status(self) -> None:
        """Write the status file if one was asked for, at most every `status_period_s`."""
        now = time.monotonic()
        if self.status_file is None or now < self._status_due:
            return
        self._status_due = now + self.status_period_s
        self.write_status()

    def write_status(self) -> None:
        """The status file, whole (a rename), readable by its owner only."""
        if self.status_file is None:
            return
        status = self.status()
        text = status_text(status) if self.status_form is None else self.status_form(status)
        tmp = self.status_file.with_name(self.status_file.name + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            os.fchmod(f.fileno(), 0o600)
            f.write(text)
        os.replace(tmp, self.status_file)


def status_text(status: dict) -> str:
    """A status dict as the status file's JSON (numpy scalars as numbers, paths as strings)."""
    return json.dumps(status, default=_jsonable)


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (Path,)):
        return str(value)
    raise TypeError(type(value).__name__)
