"""The control panel: buttons that drive the session and the figures an operator watches.

Buttons do not touch the Session: they queue Commands (gripper changes and
episode events) on `PanelDevice`, which the control loop polls like any other
device, so a click lands between two ticks and is recorded with the step it
affected. The panel's text is refreshed a few times a second from snapshots,
and only sent to browsers when it changed.
"""

from __future__ import annotations

import collections
import time

import numpy as np
import viser

from devices.command import Command
from devices.gamepad import MAPPING as GAMEPAD_MAPPING
from teleop.web.shared.loop_thread import LoopThread
from teleop.web.session_page.page_devices import CONNECT_SPACEMOUSE
from teleop.web.session_page.page_keyboard import PageKeyboardDevice

REFRESH_HZ = 4.0
POS_SPEED_RANGE = (0.01, 0.5)  # m/s
ROT_SPEED_RANGE = (0.05, 3.0)  # rad/s
LABEL_HOLD_S = 0.6  # after a click, the button shows the new label before the loop confirms it


class PanelDevice:
    """Commands from the panel's buttons, handed to the control loop at its next tick."""

    kind = "panel"

    def __init__(self, name: str = "panel") -> None:
        self.name = name
        self._queue: collections.deque[Command] = collections.deque()

    def push(self, command: Command) -> None:
        command.source = self.name
        self._queue.append(command)

    def start(self) -> None:
        pass

    def poll(self, view, dt: float) -> list[Command]:
        out = []
        while self._queue:
            out.append(self._queue.popleft())
        return out

    def status(self) -> str:
        return "ready"

    @property
    def finished(self) -> bool:
        return False

    def close(self) -> None:
        self._queue.clear()


def _fmt(value: float | None, unit: str, digits: int = 1) -> str:
    return "–" if value is None else f"{value:.{digits}f} {unit}"


class Panel(LoopThread):
    """Builds the GUI on `server` and keeps its figures current."""

    def __init__(
        self,
        server: viser.ViserServer,
        app,  # teleop.web.session_page.app.WebApp: sim, drawer, devices, problems, figures
        cameras: tuple[str, ...],
        pos_speed: float,
        rot_speed: float,
    ) -> None:
        self.server = server
        self.app = app
        self.device: PanelDevice = app.panel_device
        self._label_hold_until = 0.0
        self._texts: dict[str, str] = {}
        self._init_thread("teleop-panel")
        gui = server.gui
        snap = app.sim.snapshot
        recording_on = app.session.recorder is not None

        self.task_md = gui.add_markdown(self._task_text(snap))
        self.policy_md = self.handback_btn = self.takeover_btn = None
        if app.takeover is not None:
            with gui.add_folder("Policy"):
                self.policy_md = gui.add_markdown(self._policy_text())
                self.handback_btn = gui.add_button("Hand back to policy", color="green",
                                                   hint="the policy drives again from here (key p)")
                self.takeover_btn = gui.add_button("Take over", hint="stop the policy; you drive (any device does this too)")
        with gui.add_folder("Episode"):
            self.record_btn = gui.add_button("Record", color="red", disabled=not recording_on,
                                             hint="start recording an episode; click Stop to save it")
            self.save_btn = gui.add_button("Save", disabled=not recording_on, hint="save the episode being recorded")
            self.discard_btn = gui.add_button("Discard", disabled=not recording_on, hint="drop the episode being recorded")
            self.reset_btn = gui.add_button("Reset", hint="new object placement (next seed); saves an episode in progress")
            self.episode_md = gui.add_markdown(self._episode_text(snap))
        self.gripper_buttons: list[tuple[viser.GuiButtonHandle, viser.GuiButtonHandle]] = []
        for arm in range(app.session.controller.n_arms):
            title = "Gripper" if app.session.controller.n_arms == 1 else f"Gripper (arm {arm})"
            with gui.add_folder(title):
                self.gripper_buttons.append((gui.add_button("Open"), gui.add_button("Close")))
        with gui.add_folder("Loop"):
            self.loop_md = gui.add_markdown(self._loop_text(snap))
        with gui.add_folder("Camera"):
            first = "room" if "room" in cameras else cameras[0] if cameras else "none"  # the wide view, for people
            self.camera_dropdown = gui.add_dropdown("Camera", options=cameras or ("none",), initial_value=first)
            w, h = app.camera_size
            self.camera_image = gui.add_image(np.zeros((h, w, 3), dtype=np.uint8), format="jpeg", jpeg_quality=80)
            self.camera_md = gui.add_markdown("")
        with gui.add_folder("Speed (keyboard, SpaceMouse)"):
            self.pos_slider = gui.add_slider("Position (m/s)", min=POS_SPEED_RANGE[0], max=POS_SPEED_RANGE[1],
                                             step=0.01, initial_value=float(np.clip(pos_speed, *POS_SPEED_RANGE)))
            self.rot_slider = gui.add_slider("Rotation (rad/s)", min=ROT_SPEED_RANGE[0], max=ROT_SPEED_RANGE[1],
                                             step=0.05, initial_value=float(np.clip(rot_speed, *ROT_SPEED_RANGE)))
        with gui.add_folder("Devices"):
            self.devices_md = gui.add_markdown(self._devices_text())
            if app.page_inputs.webhid is not None:
                # The page's script asks the browser for the device in this click (WebHID needs a user gesture).
                gui.add_button(CONNECT_SPACEMOUSE, hint="a SpaceMouse plugged into this computer (WebHID: Chrome, Edge)")
            if app.phone_url is not None:
                gui.add_markdown(f"Phone: open `{app.phone_url}` on the phone (https or a tunnel to localhost: see docs/session.md)")
            for path, url in app.companion_urls.items():  # the XR page: a link here, its address for a headset
                gui.add_markdown(f"[XR headset]({path}): open `{url}` in the headset's browser (docs/xr.md)")
            if app.page_inputs.gamepad is not None:
                gui.add_markdown("Gamepad: " + " · ".join(f"**{control}** {action}" for control, action in GAMEPAD_MAPPING))
        self.notes_md = gui.add_markdown("")
        self._wire()

    # -- callbacks -------------------------------------------------------
    def _wire(self) -> None:
        push = self.device.push

        @self.record_btn.on_click
        def _(_) -> None:
            recording = self.app.sim.snapshot.recording
            push(Command(events=("save",) if recording else ("start",)))
            self._hold_label("Record" if recording else "Stop")

        @self.save_btn.on_click
        def _(_) -> None:
            push(Command(events=("save",)))
            self._hold_label("Record")

        @self.discard_btn.on_click
        def _(_) -> None:
            push(Command(events=("discard",)))
            self._hold_label("Record")

        @self.reset_btn.on_click
        def _(_) -> None:
            push(Command(events=("reset",)))
            self._hold_label("Record")

        if self.handback_btn is not None:
            # As the keyboard's `p`: an event the loop sees in the tick it is applied.
            self.handback_btn.on_click(lambda _: push(Command(events=("policy",))))
            self.takeover_btn.on_click(lambda _: self.app.takeover.request("operator"))

        for arm, (open_btn, close_btn) in enumerate(self.gripper_buttons):
            open_btn.on_click(lambda _, arm=arm: push(Command(gripper="open", arm=arm)))
            close_btn.on_click(lambda _, arm=arm: push(Command(gripper="close", arm=arm)))

        @self.pos_slider.on_update
        def _(_) -> None:
            self.app.set_speeds(pos_speed=float(self.pos_slider.value))

        @self.rot_slider.on_update
        def _(_) -> None:
            self.app.set_speeds(rot_speed=float(self.rot_slider.value))

    def _hold_label(self, label: str) -> None:
        self.record_btn.label = label
        self._label_hold_until = time.monotonic() + LABEL_HOLD_S

    @property
    def camera_name(self) -> str:
        return str(self.camera_dropdown.value)

    def show_image(self, image: np.ndarray) -> None:
        self.camera_image.image = image

    def camera_note(self, text: str) -> None:
        """A line under the picture, as a failure's ("" for none): why it comes slower, say."""
        self.camera_md.content = f"*{text}*" if text else ""

    def camera_failed(self, message: str) -> None:
        self.camera_image.visible = False
        self.camera_md.content = f"*{message}*"

    # -- text ------------------------------------------------------------
    def _task_text(self, snap) -> str:
        s = self.app.session
        state = "**succeeding**" if snap.success else "not yet"
        text = f"**Task:** {s.scene.instruction}  \n**Success:** {state} · scene `{s.scene_name}` · robot `{s.robot.name}` · seed {snap.seed}"
        return text if self.app.headline is None else f"{text}  \n{self.app.headline()}"

    def _policy_text(self) -> str:
        t = self.app.takeover
        if t.driver == "policy":
            head = "**Driving: policy** · touch any device (gizmo, key, SpaceMouse, gripper) to take over"
        else:
            head = "**Driving: operator** · press **p** or *Hand back to policy* to give control back"
        median, worst = t.inference_ms()
        lines = [
            head,
            f"Inference: **{_fmt(median, 'ms')}** median, {_fmt(worst, 'ms')} max · observation {_fmt(t.observe_ms(), 'ms')}",
            f"Takeovers: {t.takeovers} · steps by policy {t.policy_steps}, by operator {t.operator_steps}",
            f"`{t.policy.name}`",
        ]
        if t.problem:
            lines.append(f"**Policy stopped:** {t.problem}")
        return "  \n".join(lines)

    def _episode_text(self, snap) -> str:
        app = self.app
        recorder = app.session.recorder
        if recorder is None:
            head = "Not recording: start with `--record DIR` to record episodes."
        elif snap.recording:
            head = f"**● Recording** step {snap.episode_steps} ({snap.episode_steps * app.session.dt:.1f} s)"
        else:
            head = f"Ready to record into `{recorder.directory}`"
        lines = [head]
        if recorder is not None and not snap.recording:
            lines.append(self._next_episode_text(snap))
        if snap.recording_error and not snap.recording:
            lines.append(f"**Recording stopped:** {snap.recording_error}")
        lines += [f"Saved: **{snap.episodes_saved}** · Discarded: **{snap.episodes_discarded}**"]
        last = app.last_saved_line()
        if last:
            lines.append(last)
        return "  \n".join(lines)

    def _next_episode_text(self, snap) -> str:
        """Where the next episode starts: its seed's initial state, or (--keep-scene) the scene as it is."""
        if self.app.session.fresh_episodes:
            return f"Next episode: **seed {snap.seed}**, from its initial state (Record puts the arm home)"
        return f"Next episode: seed {snap.seed}, from the scene as it is now (`--keep-scene`)"

    def _devices_text(self) -> str:
        rows = []
        for d in self.app.devices:
            problem = self.app.sim.device_problems.get(d.name)
            rows.append(f"- **{d.name}**: {problem or d.status()}")
        keys = self.app.page_keys
        if keys is not None and not isinstance(keys.keyboard, PageKeyboardDevice):
            rows.append(f"- **{keys.keyboard.name}** also reads {keys.describe()}")  # pages feed this machine's keyboard
        for line in self.app.device_problems:
            name, _, reason = line.partition(": ")
            rows.append(f"- **{name}**: not started ({reason})")
        follower = getattr(self.app, "follower", None)
        if follower is not None:
            rows.append(f"- {follower.line()}")  # "follower: tracking, gap 1.2 deg"
        return "\n".join(rows) or "no devices"

    def _loop_text(self, snap) -> str:
        app = self.app
        sim = app.sim
        errors = ", ".join(f"{e * 1000:.1f}" for e in snap.tracking_error_m)
        return "  \n".join([
            f"Loop: **{sim.loop_hz():.1f} Hz** (target {app.session.control_hz:g}) · tick {sim.compute_ms():.2f} ms · "
            f"headroom {sim.headroom():.0f}x",
            f"IK error: **{errors} mm** · IK failures {snap.ik_failures}",
            f"Latency (input → drawn): **{_fmt(app.drawer.latency_ms, 'ms')}** · scene update {app.drawer.update_ms():.2f} ms",
            f"Browsers: {len(self.server.get_clients())}" + (
                f" · {len(app.software_views)} drawing without a GPU (half resolution, no shadows or environment light there)"
                if app.software_views else ""),
        ])

    def _set(self, key: str, handle, text: str) -> None:
        if self._texts.get(key) != text:
            self._texts[key] = text
            handle.content = text

    def refresh(self) -> None:
        snap = self.app.sim.snapshot
        self._set("task", self.task_md, self._task_text(snap))
        if self.policy_md is not None:
            self._set("policy", self.policy_md, self._policy_text())
            self.handback_btn.disabled = self.app.takeover.driver == "policy" or self.app.takeover.problem is not None
            self.takeover_btn.disabled = self.app.takeover.driver == "operator"
        self._set("episode", self.episode_md, self._episode_text(snap))
        self._set("devices", self.devices_md, self._devices_text())
        self._set("loop", self.loop_md, self._loop_text(snap))
        notes = self.app.notes()
        self._set("notes", self.notes_md, "  \n".join(f"*{n}*" for n in notes[-4:]))
        if time.monotonic() > self._label_hold_until:
            label = "Stop" if snap.recording else "Record"
            if self.record_btn.label != label:
                self.record_btn.label = label

    # -- thread ----------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.wait(1.0 / REFRESH_HZ):
            try:
                with self.server.atomic():  # the texts that changed reach the pages together, waking viser once
                    self.refresh()
                self.app.tick_status()
            except Exception as exc:  # noqa: BLE001 - the panel must not end the session
                print(f"panel refresh failed: {type(exc).__name__}: {exc}")
