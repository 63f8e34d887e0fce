"""A recorded episode in the browser: the scene at any step, a timeline, play/pause and speed.

`teleop replay PATH --serve` calls `serve_episode`. Each step is shown by
restoring its recorded state (mj_setState + mj_kinematics, nothing is
re-simulated), so what you scrub through is exactly what was recorded. The
target and actual end-effector poses are drawn as in the live session.
The episode's subtasks are drawn under the timeline and edited and saved in
the Subtasks folder (replay/viewer_subtasks.py).

This module sits under `replay` and so does not import `teleop`: errors are
printed as one line and returned as exit code 2, the way the CLI reports
user errors.
"""

from __future__ import annotations

import copy
import sys
import threading
import time

import mujoco
import numpy as np

from replay.episode import Episode, EpisodeError
from replay.listen import ListenError, check_port_free, is_loopback
from replay.viewer_subtasks import SubtaskPanel
from scenes.errors import TeleopError

SPEEDS = ("0.25x", "0.5x", "1x", "2x", "4x")
CAMERA_POSITION = (1.45, -1.05, 0.95)
CAMERA_LOOK_AT = (0.35, 0.0, 0.2)


class ServeError(TeleopError):
    """The viewer cannot start (port taken, bad host, empty episode); one line for the user."""


class EpisodeViewer:
    """The scene of `episode` at a chosen step, with a timeline that plays at a chosen speed."""

    def __init__(self, server, episode: Episode) -> None:
        from mjviser import ViserMujocoScene

        if episode.steps == 0:
            raise ServeError(f"{episode.path}: the episode has no steps to show")
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
        server.initial_camera.position = CAMERA_POSITION
        server.initial_camera.look_at = CAMERA_LOOK_AT
        server.initial_camera.up = (0.0, 0.0, 1.0)
        self.scene = ViserMujocoScene(server, self.model, num_envs=1)
        self.scene.camera_tracking_enabled = False
        n_arms = episode.ee_target.shape[1] if episode.ee_target.ndim == 3 else 0
        self.targets = server.scene.add_batched_axes(
            "/markers/targets", batched_wxyzs=np.tile([1.0, 0, 0, 0], (n_arms, 1)),
            batched_positions=np.zeros((n_arms, 3)), axes_length=0.05, axes_radius=0.003)
        self.ee_lines = server.scene.add_line_segments(
            "/markers/error", points=np.zeros((n_arms, 2, 3)), colors=np.tile((255, 60, 60), (n_arms, 2, 1)).astype(np.uint8),
            thickness=3.0, thickness_units="screen")
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
            if ep.ee_target.ndim == 3 and ep.ee_target.shape[1]:
                self.targets.batched_positions = ep.ee_target[step, :, :3]
                self.targets.batched_wxyzs = ep.ee_target[step, :, 3:7]
                self.ee_lines.points = np.stack([ep.ee_pose[step, :, :3], ep.ee_target[step, :, :3]], axis=1)
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


def serve_episode(episode: Episode, host: str = "127.0.0.1", port: int = 8080,
                  stop: threading.Event | None = None) -> int:
    """Serve `episode` on host:port until Ctrl-C (a KeyboardInterrupt) or `stop` is set (the CLI's
    token, set on Ctrl-C and SIGTERM); returns the exit code (2 for a user error)."""
    import viser

    try:
        try:
            check_port_free(host, port)
        except ListenError as exc:
            raise ServeError(str(exc)) from None
        server = viser.ViserServer(host=host, port=port, label="teleop replay", verbose=False)
        if server.get_port() != port:
            server.stop()
            raise ServeError(f"port {port} is already in use on {host}; pass --port N")
        try:
            server.gui.configure_theme(show_logo=False, show_share_button=False)
            server.gui.main_panel.dock_right()
            viewer = EpisodeViewer(server, episode)
        except BaseException:
            server.stop()
            raise
    except (ServeError, EpisodeError) as exc:
        print(f"teleop replay: error: {exc}", file=sys.stderr)
        return 2
    if not is_loopback(host):
        print(f"warning: listening on {host}:{port}: anyone who can reach this port can see this episode", file=sys.stderr)
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
    print(f"open http://{shown}:{port} in a browser to view {episode.path.name} (Ctrl-C to stop)", flush=True)
    if stop is not None:  # the token ends the play loop
        threading.Thread(target=lambda: (stop.wait(), viewer.stop()), name="viewer-stop", daemon=True).start()
    try:
        viewer.run()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
        server.stop()
    return 0
