"""The planner an `instruct:` device plays: the scene seen (or read from the state), the sentence grounded and planned.

`make_planner` is what `teleop run` / `teleop serve` hand the device registry (devices.registry
DeviceOptions.planner); it runs when each episode begins and writes a note of the plan (the
instruction, the actions, the positions it used, the steps) into the episode as its `generator`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from devices.planned import Planner
from devices.script import ScriptStep
from devices.view import SessionView
from teleop.instruct.grammar import GroundingError, parse
from teleop.instruct.perceive import RgbdCamera, perceive, scene_objects
from teleop.instruct.plan_url import plan_from_url
from teleop.instruct.planner import checked, from_perception, plan_steps, state_positions

GENERATOR = "teleop.instruct"


@dataclass(frozen=True)
class InstructOptions:
    """Where positions come from and who plans (`--instruct-state`, `--instruct-camera`, `--plan-url`)."""

    state: bool = False  # positions from the simulator's state instead of the camera
    camera: str = "front"
    size: int = 224  # px, the square RGB-D view
    plan_url: str | None = None  # an OpenAI-compatible chat endpoint; None: the rule planner


def make_planner(instruction: str, options: InstructOptions, on_note: Callable[[Mapping[str, Any]], None] | None = None
                 ) -> Planner:
    """A planner for `instruction`; `on_note` gets each plan's note (the app stores it in the episode)."""
    cameras: dict[str, RgbdCamera] = {}

    def plan(view: SessionView) -> tuple[list[ScriptStep], Mapping[str, Any]]:
        scene, model, data = view.scene, view.model, view.data  # the app's view is the Controller
        objects = scene_objects(scene.task)
        actions = [] if options.plan_url else parse(instruction, objects)
        names = [o.name for o in objects]
        wanted = list(dict.fromkeys(n for a in actions for n in (a.obj, a.target) if n)) if actions else names
        status: dict[str, str] = {}
        if options.state:
            where = state_positions(model, data, wanted)
        else:
            if "rgbd" not in cameras:
                cameras["rgbd"] = RgbdCamera(model, options.size, options.size)
            else:
                cameras["rgbd"].load(model)
            seen = perceive(cameras["rgbd"], model, data, objects, options.camera)
            status = {n: e.status for n, e in seen.estimates.items()}
            if options.plan_url:
                wanted = [n for n in names if seen.estimates[n].position is not None]
            where = from_perception(seen, wanted)
        home = view.target_pose(0)[0]
        if options.plan_url:
            steps, raw = plan_from_url(options.plan_url, instruction, objects, where, home)
        else:
            raw = plan_steps(actions, where, home)
            steps = checked(raw, "the instruct plan")
        note = {
            "name": GENERATOR,
            "instruction": instruction,
            "planner": options.plan_url or "rules",
            "positions": "state" if options.state else f"camera:{options.camera}",
            "actions": [a.text() for a in actions],
            "objects": {n: {**loc.as_json(), **({"status": status[n]} if n in status else {})} for n, loc in where.items()},
            "steps": raw,
        }
        if on_note is not None:
            on_note(note)
        return steps, note

    return plan


__all__ = ["GroundingError", "InstructOptions", "make_planner"]
