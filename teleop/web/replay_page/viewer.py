"""A recorded episode in the browser: the scene at any step, a timeline, play/pause and speed.

`teleop replay PATH --serve` calls `serve_episode`. Each step is shown by
restoring its recorded state (mj_setState + mj_kinematics, nothing is
re-simulated), so what you scrub through is exactly what was recorded. The
target and actual end-effector poses are drawn as in the live session.
The episode's subtasks are drawn under the timeline and edited and saved in
the Subtasks folder (teleop/web/replay_page/subtasks.py).

The viewer serves behind the session's gate (teleop.web.shared.access): a token off
loopback, HTTP 403 and refused websockets without it, the per-port cookie and
the Origin check. Its page can write the subtask file, and it does so only from
a panel event, which arrives over viser's websocket and so past that gate.
Camera and markers are the live session's (teleop.web.shared.camera_markers), and
so is the lighter view for a browser drawing WebGL in software
(teleop.web.shared.view_quality): without it such a page draws viser's
shadows and environment light without pause, ~0.8 s a frame, and a click on
the timeline waits behind it. The page learns that, and gets the banner when
the server is gone, from the session's input script run with no keys bound.
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Callable

import mujoco

from replay.episode import Episode, EpisodeError
from teleop.errors import UsageError
from teleop.web.shared.access import Gate, announce, resolve_token
from teleop.web.shared.camera_markers import Markers, place_camera
from teleop.web.shared.input_channel import PATH as INPUT_PATH
from teleop.web.shared.input_channel import InputChannel, channel_script
from teleop.web.shared.view_quality import SoftwareViews, ViewReports, head_script
from teleop.web.viser_internals.guarded_start import start_guarded
from teleop.web.viser_internals.page_script import run_javascript
from teleop.web.shared.net import check_port_free
from teleop.web.replay_page.subtasks import SubtaskPanel

SPEEDS = ("0.25x", "0.5x", "1x", "2x", "4x")
VIEWER_REACH = "see this episode and overwrite its subtask file"  # for the --no-token warning


class EpisodeViewer:
    """The scene of `episode` at a chosen step, with a timeline that plays at a chosen speed."""

    def __init__(self, server, episode: Episode) -> None:
        from mjviser import ViserMujocoScene

        if episode.steps == 0:
            raise UsageError(f"{episode.path}: the episode has no steps to show")
        self.server = server
        self.episode = episode
        self.model = copy.copy(episode.build_model())
        self.data = mujoco.MjData(self.model)
        self.dt = (episode.meta.timestep or self.model.opt.timestep) * episode.substeps
        self.step = 0
        self.playing = False
        self.speed = 1.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        place_camera(server)
        self.scene = ViserMujocoScene(server, self.model, num_envs=1)
        self.scene.camera_tracking_enabled = False
        n_arms = episode.ee_target.shape[1] if episode.ee_target.ndim == 3 else 0
        self.markers = Markers(server, n_arms) if n_arms else None
        self.subtasks = SubtaskPanel(server.gui, episode, self.model, self.dt, current_step=lambda: self.step,
                                     jump=self.show)
        self._build_gui()
        self.show(0)

    def _build_gui(self) -> None:
        gui = self.server.gui
        ep = self.episode
        meta = ep.meta
        state = "complete" if meta.complete else "incomplete"
        success = "succeeded" if meta.success else "did not succeed"
        gui.add_markdown(
            f"**{ep.path.name}**  \n{meta.task}  \n"
            f"{ep.steps} steps, {ep.seconds:.2f} s at {meta.control_hz:g} Hz · {state} · {success}"
            + (" · *file was cut short*" if ep.truncated else "")
        )
        self.slider = gui.add_slider("Step", min=0, max=max(ep.steps - 1, 1), step=1, initial_value=0)
        self.subtasks.add_timeline()
        self.time_md = gui.add_markdown("")
        self.play_btn = gui.add_button("Play")
        self.speed_dd = gui.add_dropdown("Speed", options=SPEEDS, initial_value="1x")
        self.subtasks.add_folder()

        @self.slider.on_update
        def _(_) -> None:
            value = int(self.slider.value)
            if value != self.step:
                self.show(value)

        @self.play_btn.on_click
        def _(_) -> None:
            self.set_playing(not self.playing)

        @self.speed_dd.on_update
        def _(_) -> None:
            self.speed = float(str(self.speed_dd.value).rstrip("x"))

    def set_playing(self, playing: bool) -> None:
        if playing and self.step >= self.episode.steps - 1:
            self.show(0)  # play again from the start
        self.playing = playing
        self.play_btn.label = "Pause" if playing else "Play"

    def show(self, step: int) -> None:
        """Draw the recorded state of `step` (clamped to the episode)."""
        ep = self.episode
        step = int(min(max(step, 0), ep.steps - 1))
        with self._lock:
            self.step = step
            mujoco.mj_setState(self.model, self.data, ep.state[step], mujoco.mjtState.mjSTATE_INTEGRATION)
            mujoco.mj_kinematics(self.model, self.data)
            if self.markers is not None:
                self.markers.draw(ep.ee_target[step], ep.ee_pose[step])
            self.scene.update_from_mjdata(self.data)
            self.server.flush()  # mjviser flushes inside its atomic block, too early for viser's sender
            if int(self.slider.value) != step:
                self.slider.value = step
            self.subtasks.show_step(step)
            self.time_md.content = f"t = {step * self.dt:.2f} s / {ep.seconds:.2f} s · {self.subtasks.label(step)}"

    def run(self) -> None:
        """Play when asked, until `stop()`: steps advance with wall time x speed."""
        last = time.monotonic()
        carry = 0.0
        while not self._stop.wait(1.0 / 60.0):
            now = time.monotonic()
            elapsed, last = now - last, now
            if not self.playing:
                carry = 0.0
                continue
            carry += elapsed * self.speed / self.dt
            advance = int(carry)
            if advance:
                carry -= advance
                target = self.step + advance
                if target >= self.episode.steps - 1:
                    self.show(self.episode.steps - 1)
                    self.set_playing(False)
                else:
                    self.show(target)

    def stop(self) -> None:
        self._stop.set()


def serve_episode(episode: Episode, host: str = "127.0.0.1", port: int = 8080, token: str | None = None,
                  no_token: bool = False, stop: threading.Event | None = None,
                  log: Callable[[str], None] | None = None) -> int:
    """Serve `episode` on host:port until Ctrl-C (a KeyboardInterrupt) or `stop` is set (the CLI's
    token, set on Ctrl-C and SIGTERM); returns 0. A user error (bad token or port, empty episode)
    raises UsageError.

    token / no_token: as for `teleop serve` (teleop.web.shared.access.resolve_token): a token is
    required off loopback (random unless given or in TELEOP_TOKEN), and the printed URL carries it.
    """
    import viser

    log = log or (lambda line: print(line, flush=True))
    token = resolve_token(host, token, no_token)
    check_port_free(host, port)
    channel = InputChannel()  # the page's report of how it draws; it binds no keys
    server = start_guarded(lambda: viser.ViserServer(host=host, port=port, label="teleop replay", verbose=False),
                           lambda started: started.stop(), Gate.for_server(host, port, token),
                           routes={INPUT_PATH: channel.handle}, head=head_script())
    try:
        views = SoftwareViews(server)
        channel.listener = ViewReports(views, log)
        # viser has no public call to run a script in a page (teleop.web.viser_internals.page_script)
        server.on_client_connect(lambda client: run_javascript(client, channel_script(client.client_id, keys=[])))
        server.on_client_disconnect(lambda client: views.forget(client.client_id))
        if server.get_port() != port:  # someone took it between our check and viser's bind
            raise UsageError(f"port {port} is already in use on {host}; stop what uses it or pass --port N")
        server.gui.configure_theme(show_logo=False, show_share_button=False)
        server.gui.main_panel.dock_right()
        viewer = EpisodeViewer(server, episode)
    except EpisodeError as exc:
        server.stop()
        raise UsageError(str(exc)) from None
    except BaseException:
        server.stop()
        raise
    announce(host, port, token, f"view {episode.path.name}", VIEWER_REACH, log)
    if stop is not None:  # the cancellation token ends the play loop
        threading.Thread(target=lambda: (stop.wait(), viewer.stop()), name="viewer-stop", daemon=True).start()
    try:
        viewer.run()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
        server.stop()
    return 0
