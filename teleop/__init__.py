"""Teleoperate MuJoCo robot arms, record demonstrations that replay bit for bit, export datasets.

`import teleop` is the one import a script needs::

    import teleop
    session = teleop.Session(scene="lift", robot="panda", seed=0, control_hz=30)
    script = teleop.ScriptDevice("scenes/scripts/lift_pick.json")
    with teleop.Recorder(session, "episodes", formats=("mcap", "hdf5")) as rec:
        result = teleop.run_episode(session, [script])
    episode = teleop.load_episode(rec.paths[0])
    assert teleop.resimulate(episode).bit_exact

Units everywhere: metres, radians, seconds; poses in the world frame (x away
from the robot's base, z up) with wxyz quaternions, as MuJoCo writes them.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

from devices.base import Device, DeviceError
from devices.command import Command
from devices.gizmo import GizmoDevice
from devices.keyboard import KeyboardDevice
from devices.script import ScriptDevice
from devices.spacemouse import SpaceMouseDevice
from recorder.format import EpisodeMeta
from replay import Episode, VerifyResult, load_episode, replay_states, resimulate
from replay.export.dataset import ExportOptions, ExportSummary, export_dataset
from scenes.errors import TeleopError
from teleop.control.controller import Controller, StepResult
from teleop.control.loop import EpisodeResult, run_episode
from teleop.control.recording import Recorder
from teleop.control.session import Session

__all__ = [
    "Command",
    "Controller",
    "Device",
    "DeviceError",
    "Episode",
    "EpisodeMeta",
    "EpisodeResult",
    "ExportSummary",
    "GizmoDevice",
    "KeyboardDevice",
    "Recorder",
    "ScriptDevice",
    "Session",
    "SpaceMouseDevice",
    "StepResult",
    "TeleopError",
    "VerifyResult",
    "export_lerobot",
    "load_episode",
    "replay_states",
    "resimulate",
    "run_episode",
    "serve",
]


def export_lerobot(
    paths: Iterable[str | Path],
    out: str | Path,
    repo_id: str,
    cameras: Sequence[str] | None = None,
    image_size: tuple[int, int] = (224, 224),
    action: str = "joint",
    task: str | None = None,
    only_success: bool = False,
    video: bool = True,
    vcodec: str | None = None,
    append: bool = False,
    progress: bool = False,
) -> ExportSummary:
    """Write recorded episodes (files or folders) into a LeRobot dataset at `out`.

    Camera images (`cameras`; "wrist" means every arm's wrist camera) are
    rendered from the recorded states at `image_size` (width, height) pixels.
    action: "joint" (recorded joint targets + gripper), "ee_pose" (commanded EE
    pose) or "ee_delta" (commanded minus actual EE pose, m and rotation vector).
    Needs the `lerobot` extra.
    """
    options = ExportOptions(
        out=Path(out),
        repo_id=repo_id,
        cameras=list(cameras) if cameras is not None else None,
        image_size=(int(image_size[0]), int(image_size[1])),
        action=action,
        task=task,
        only_success=only_success,
        video=video,
        vcodec=vcodec,
        append=append,
        progress=progress,
    )
    return export_dataset(list(paths), options)


def __getattr__(name: str):
    """`teleop.web.serve` loads the browser server (viser, mjviser: 1-2 s) on first use, so
    `import teleop` and the command line stay quick for everything that does not serve."""
    if name == "serve":
        from teleop.web.serve import serve  # lazy: heavy, and only a browser session needs it

        return serve
    raise AttributeError(f"module 'teleop' has no attribute {name!r}")
