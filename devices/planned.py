"""A device that plays a plan made when each episode begins: `--device "instruct:put the blue cube on the red cylinder"`.

The plan is the script engine's steps (devices/script.py), made by a planner the app hands in
(teleop.instruct: perception from a camera and a rule or chat-endpoint planner), so this module
needs nothing above devices/. The planner runs in `check`, before the episode's first tick and
before anything is recorded: a sentence it cannot ground stops the run with one line.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from devices.command import Command
from devices.script import ScriptDevice, ScriptStep
from devices.view import SessionView

# (the session's view) -> (the steps to play, a note of the plan for the episode)
Planner = Callable[[SessionView], tuple[list[ScriptStep], Mapping[str, Any]]]


class PlannedDevice(ScriptDevice):
    """Plays the steps a planner made from an instruction, planning again at each episode (new seed, new poses)."""

    kind = "script"

    def __init__(self, instruction: str, planner: Planner) -> None:
        self.instruction = instruction
        self.planner = planner
        self.path = Path("instruct")
        self.name = "instruct"
        self.steps: list[ScriptStep] = []
        self.note: Mapping[str, Any] = {}
        self.stale = True  # the steps are not yet planned for the scene now
        self.restart()

    def restart(self) -> None:
        """Play from the first step, planned again for the scene as it will be at the next poll or check."""
        super().restart()
        self.stale = True

    def check(self, view: SessionView) -> None:
        """Plan for the scene as it is now (before the first tick), then check the plan's arms and bodies as a script's."""
        self.plan(view)

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        if self.stale:  # a new scene the session did not check devices on (the browser session's next episode)
            self.plan(view)
        return super().poll(view, dt)

    def plan(self, view: SessionView) -> None:
        self.steps, self.note = self.planner(view)
        super().restart()
        self.stale = False
        super().check(view)
