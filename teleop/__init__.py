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

import dataclasses
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scenes.lazy_names import lazy_names

if TYPE_CHECKING:
    from devices.base import Device, DeviceError
    from devices.command import Command
    from devices.gizmo import GizmoDevice
    from devices.keyboard import KeyboardDevice
    from devices.script import ScriptDevice
    from devices.spacemouse import SpaceMouseDevice
    from replay import Episode, VerifyResult, load_episode, replay_states, resimulate
    from replay.episode import EpisodeMeta
    from replay.export import ExportOptions, ExportSummary
    from scenes.errors import TeleopError
    from teleop.control.controller import Controller, StepResult
    from teleop.control.loop import EpisodeResult, run_episode
    from teleop.control.recording import Recorder
    from teleop.control.session import Session
    from teleop.web.session_page.serve_options import ServeOptions

# Each name's module, imported at the first use of the name (PEP 562): `teleop --help` and a command that stops
# at a bad flag need none of MuJoCo, mink or LeRobot, and start in a fraction of a second.
_HOMES = {
    "Command": "devices.command",
    "Controller": "teleop.control.controller",
    "Device": "devices.base",
    "DeviceError": "devices.base",
    "Episode": "replay",
    "EpisodeMeta": "replay.episode",
    "EpisodeResult": "teleop.control.loop",
    "ExportOptions": "replay.export",
    "ExportSummary": "replay.export",
    "GizmoDevice": "devices.gizmo",
    "KeyboardDevice": "devices.keyboard",
    "Recorder": "teleop.control.recording",
    "ScriptDevice": "devices.script",
    "ServeOptions": "teleop.web.session_page.serve_options",
    "Session": "teleop.control.session",
    "SpaceMouseDevice": "devices.spacemouse",
    "StepResult": "teleop.control.controller",
    "TeleopError": "scenes.errors",
    "VerifyResult": "replay",
    "load_episode": "replay",
    "replay_states": "replay",
    "resimulate": "replay",
    "run_episode": "teleop.control.loop",
}


__getattr__, __dir__ = lazy_names(__name__, _HOMES, globals())


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
    "ServeOptions",
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
    out: str | Path | None = None,
    repo_id: str | None = None,
    *,
    options: ExportOptions | None = None,
    **fields: Any,
) -> ExportSummary:
    """Write recorded episodes (files or folders) into a LeRobot dataset at `out`.

    Every export option is reachable, as `teleop export` has it: pass `options` (a
    `teleop.ExportOptions`, from `replay.export.options`) and/or any of its fields as
    keywords, which win over `options`. Among them: camera images (`cameras`; "wrist"
    means every arm's wrist camera) rendered from the recorded states at `image_size`
    (width, height) pixels; action: "joint" (recorded joint targets + gripper), "ee_pose"
    (commanded EE pose) or "ee_delta" (commanded minus actual EE pose, m and rotation
    vector); `workers` / `ray` (shards in parallel); `object_state`; `video` / `vcodec`;
    `append`. The progress bar is off unless `progress=True`. A keyword that is no field
    raises TypeError naming it. Needs the `lerobot` extra.
    """
    from replay.export import ExportOptions, export_dataset

    known = {f.name for f in dataclasses.fields(ExportOptions)}
    if unknown := sorted(set(fields) - known):
        raise TypeError(f"export_lerobot() got unexpected keyword argument(s) {', '.join(unknown)} "
                        f"(ExportOptions has {', '.join(sorted(known))})")
    if out is not None:
        fields["out"] = out
    if repo_id is not None:
        fields["repo_id"] = repo_id
    if "out" in fields:
        fields["out"] = Path(fields["out"])
    if fields.get("cameras") is not None:
        fields["cameras"] = list(fields["cameras"])
    if "image_size" in fields:
        width, height = fields["image_size"]
        fields["image_size"] = (int(width), int(height))
    if options is None:
        if missing := [name for name in ("out", "repo_id") if name not in fields]:
            raise TypeError(f"export_lerobot() needs {' and '.join(missing)} (or options=ExportOptions(...))")
        options = ExportOptions(**{"progress": False, **fields})
    else:
        options = dataclasses.replace(options, **fields)
    return export_dataset(list(paths), options)


def serve(session: Session, options: ServeOptions | None = None, **keywords: Any) -> int:
    """Serve `session` in the browser and block until Ctrl-C or `stop` is set, as `teleop serve` does; 0, or 1 if the loop failed.

    Every setting is reachable: pass `options` (a `teleop.ServeOptions`) and/or any of its fields as
    keywords, which win over it (`host`, `port`, `token`, `no_token` as the flags; `pos_speed` m/s,
    `rot_speed` rad/s, `status_file`, `keep_scene`, ...), and serve()'s own: `devices` (spec words such
    as "gizmo", "keyboard", and/or started devices), `problems`, `policy`, `follower`, `stop` (a
    threading.Event), `log`. Any other name raises TypeError. The browser server (viser, mjviser: 1-2 s)
    loads on the first call, so `import teleop` stays quick for everything that does not serve.
    """
    from teleop.web.session_page.serve import serve as serve_session  # lazy: heavy, and only a browser session needs it
    from teleop.web.session_page.serve_options import ServeOptions

    fields = {name: keywords.pop(name) for name in [f.name for f in dataclasses.fields(ServeOptions)] if name in keywords}
    if options is None:
        options = ServeOptions(**fields)
    elif not isinstance(options, ServeOptions):
        raise TypeError(f"serve(): options is a teleop.ServeOptions, not {type(options).__name__} (devices go by devices=...)")
    elif fields:
        options = dataclasses.replace(options, **fields)
    return serve_session(session, options, **keywords)
