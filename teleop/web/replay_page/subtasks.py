"""The replay viewer's Subtasks panel: the subtasks on the timeline, edited and saved from the browser.

Under the Step slider a bar shows the subtasks as coloured segments in
proportion to their length (steps) with the shown step marked. The Subtasks
folder lists them (steps and seconds) and edits them: move the chosen boundary
(to the slider's step, or to a typed step), add one at the slider's step,
remove one, change the object of the subtask under the slider, and save the
sidecar file (`replay.subtasks.sidecar.write_subtasks`, by "human").

Every value from the browser is checked here before it is used (a dropdown
value must be one of its options, a step a whole number inside the episode),
and a refused edit says why in the panel: nothing raises into viser's threads.
The file is written only on the Save button's click from a page: an event that
came over viser's websocket, which the viewer serves behind the token gate
(teleop.web.shared.access, teleop.web.replay_page.viewer).
"""

from __future__ import annotations

import html
import math
import threading
from collections.abc import Callable

import mujoco

from recorder.disk import cause
from replay.episode import Episode
from replay.subtasks.edit import SubtaskEdits, initial_subtasks, object_choices
from replay.subtasks.sidecar import AnnotationError, Subtask, sidecar_path, write_subtasks

PALETTE = ("#4c78a8", "#f58518", "#54a24b", "#b279a2", "#e45756", "#72b7b2", "#eeca3b", "#9d755d")
NO_BOUNDARY = "(no boundary)"
UNSAVED = "edited · **not saved yet**"


def _color(objects: list[str], name: str) -> str:
    """A fixed colour per object name (by its place among the choices), so a name keeps its colour."""
    index = objects.index(name) if name in objects else len(objects) + sum(map(ord, name))
    return PALETTE[index % len(PALETTE)]


def timeline_html(subtasks: list[Subtask], steps: int, step: int, objects: list[str]) -> str:
    """A bar of the subtasks, each as wide as its share of the steps, with a line at `step`."""
    segments = []
    for i, s in enumerate(subtasks):
        name = html.escape(s.object)
        width = 100.0 * (s.end - s.start) / steps
        segments.append(
            f'<div title="{i + 1}: {name}, steps {s.start}-{s.end}" style="width:{width:.3f}%;'
            f'background:{_color(objects, s.object)};color:#fff;font-size:11px;line-height:18px;'
            f'overflow:hidden;white-space:nowrap;text-overflow:clip;padding-left:3px;box-sizing:border-box;'
            f'border-right:1px solid #fff">{name}</div>')
    marker = 100.0 * (step + 0.5) / steps
    return (
        '<div style="position:relative;margin:2px 0.75em 4px 0.75em">'
        f'<div style="display:flex;height:18px;border-radius:3px;overflow:hidden">{"".join(segments)}</div>'
        f'<div style="position:absolute;left:{marker:.3f}%;top:-3px;width:2px;height:24px;'
        'margin-left:-1px;background:#222"></div></div>'
    )


def listing_markdown(subtasks: list[Subtask], dt: float) -> str:
    """The subtasks as lines: number, object, steps (end exclusive) and seconds."""
    return "  \n".join(
        f"{i + 1}. **{s.object}** steps {s.start}-{s.end} ({s.start * dt:.2f}-{s.end * dt:.2f} s)"
        for i, s in enumerate(subtasks))


def step_from_browser(value: object, steps: int) -> int | None:
    """A step typed in the browser as an int inside the episode, or None (dropped)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or int(value) != value:
        return None
    return int(value) if 0 <= value < steps else None


class SubtaskPanel:
    """The timeline bar and the Subtasks folder of one episode's viewer.

    `current_step()` is the viewer's shown step; `jump(step)` shows another one.
    Edits hold `_lock`; `jump` is called only after it is released (the viewer
    calls `show_step` with its own lock held).
    """

    def __init__(self, gui, episode: Episode, model: mujoco.MjModel, dt: float,
                 current_step: Callable[[], int], jump: Callable[[int], None]) -> None:
        self.gui = gui
        self.episode = episode
        self.dt = dt
        self.current_step = current_step
        self.jump = jump
        self.choices = object_choices(episode, model)
        subtasks, source, saved = initial_subtasks(episode, self.choices)
        self.state = source if saved else f"{source} · **not saved yet**"
        self.choices = list(dict.fromkeys([*self.choices, *(s.object for s in subtasks)]))
        self.edits = SubtaskEdits(subtasks, episode.steps)
        self.message = ""
        self._lock = threading.RLock()
        self._step = 0
        self.bar = None

    # --- building -------------------------------------------------------------------------------

    def add_timeline(self) -> None:
        """The bar; call right after adding the Step slider so it sits under it."""
        self.bar = self.gui.add_html(self._bar_html())

    def add_folder(self) -> None:
        """The Subtasks folder with the listing and the editing controls."""
        gui = self.gui
        with gui.add_folder("Subtasks"):
            self.listing = gui.add_markdown("")
            self.status = gui.add_markdown("")
            self.arm_dd = None
            if len(self.edits.arms) > 1:  # a two-arm task: each arm's subtasks are edited on their own
                self.arm_dd = gui.add_dropdown("Arm", options=tuple(self.edits.arms), initial_value=self.edits.arm,
                                               hint="whose subtasks the bar, the listing and the buttons show")
            self.boundary_dd = gui.add_dropdown("Boundary", options=(NO_BOUNDARY,),
                                                hint="pick a boundary: the view jumps to it")
            self.boundary_step = gui.add_number("At step", initial_value=0, min=0, max=max(self.episode.steps - 1, 1),
                                                step=1, hint="type a step to move the chosen boundary there")
            self.move_btn = gui.add_button("Move boundary here", hint="the chosen boundary goes to the shown step")
            self.remove_btn = gui.add_button("Remove boundary", hint="merge its two subtasks (the earlier one's object stays)")
            self.object_dd = gui.add_dropdown("Object", options=tuple(self.choices) or ("world",),
                                              initial_value=self._default_object(),
                                              hint="reference object of a new subtask, or for 'Set object here'")
            self.add_btn = gui.add_button("Add boundary here", hint="split the subtask under the slider at the shown step")
            self.object_btn = gui.add_button("Set object here", hint="the subtask under the slider becomes relative to Object")
            self.save_btn = gui.add_button("Save", hint=f"write {sidecar_path(self.episode.path).name}")
        self.boundary_dd.on_update(self._on_pick_boundary)
        if self.arm_dd is not None:
            self.arm_dd.on_update(self._on_pick_arm)
        self.boundary_step.on_update(self._on_boundary_step)
        self.move_btn.on_click(lambda _: self._edit(lambda: self._move(self._chosen(), self.current_step())))
        self.remove_btn.on_click(lambda _: self._edit(self._remove))
        self.add_btn.on_click(lambda _: self._edit(self._add))
        self.object_btn.on_click(lambda _: self._edit(self._set_object))
        self.save_btn.on_click(self._on_save)
        self._refresh(select=0)

    # --- showing --------------------------------------------------------------------------------

    def label(self, step: int) -> str:
        """'object (i/n)' of the subtask holding `step`, for the time line of the panel."""
        with self._lock:
            i = self.edits.index_at(step)
            return f"{self.edits.subtasks[i].object} ({i + 1}/{len(self.edits.subtasks)})"

    def show_step(self, step: int) -> None:
        """Move the bar's marker to `step`."""
        with self._lock:
            self._step = step
            if self.bar is not None:
                content = self._bar_html()
                if self.bar.content != content:
                    self.bar.content = content

    def _bar_html(self) -> str:
        return timeline_html(self.edits.subtasks, self.episode.steps, self._step, self.choices)

    def _options(self) -> tuple[str, ...]:
        return tuple(f"{i + 1}: step {b} ({b * self.dt:.2f} s)" for i, b in enumerate(self.edits.boundaries)) or (NO_BOUNDARY,)

    def _refresh(self, select: int | None = None, sync_step: bool = True) -> None:
        """Redraw the listing, status, bar and boundary controls after an edit (lock held).

        sync_step=False leaves the "At step" field alone: the user may be typing in it.
        """
        subs = self.edits.subtasks
        self.listing.content = listing_markdown(subs, self.dt)
        self.status.content = f"{len(subs)} subtask{'s' * (len(subs) != 1)}, {self.state}" + (
            f"  \n{self.message}" if self.message else "")
        if self.bar is not None:
            self.bar.content = self._bar_html()
        options = self._options()
        keep = self._chosen() if select is None else select
        self.boundary_dd.options = options
        has = bool(self.edits.boundaries)
        self.boundary_dd.value = options[min(max(keep, 0), len(options) - 1)]
        for handle in (self.boundary_dd, self.boundary_step, self.move_btn, self.remove_btn):
            handle.disabled = not has
        if has and sync_step:
            self.boundary_step.value = self.edits.boundaries[self._chosen()]

    def _chosen(self) -> int:
        """The index of the boundary picked in the dropdown (0 when none)."""
        options = self.boundary_dd.options
        value = self.boundary_dd.value
        return options.index(value) if value in options and value != NO_BOUNDARY else 0

    def _default_object(self) -> str:
        """The first declared object not used yet, else the last subtask's object."""
        used = {s.object for s in self.edits.subtasks}
        unused = [c for c in self.choices if c not in used]
        return (unused or [self.edits.subtasks[-1].object])[0] if self.choices else "world"

    # --- editing --------------------------------------------------------------------------------

    def _edit(self, action: Callable[[], tuple[str, int | None]]) -> None:
        """Run one edit under the lock; a refusal becomes the panel's message, never a traceback."""
        with self._lock:
            try:
                message, select = action()
            except AnnotationError as exc:
                self.message = f"refused: {exc}"
                select = None
            else:
                self.message = message
                self.state = UNSAVED
            self._refresh(select)
        self.jump(self.current_step())  # the time line names the subtask under the slider

    def _move(self, i: int, step: int) -> tuple[str, int]:
        self.edits.move(i, step)
        return f"boundary {i + 1} moved to step {step}", i

    def _remove(self) -> tuple[str, int]:
        i = self._chosen()
        self.edits.remove(i)
        return f"boundary {i + 1} removed", max(i - 1, 0)

    def _add(self) -> tuple[str, int]:
        obj = self._object()
        step = self.current_step()
        i = self.edits.add(step, obj)
        return f"boundary added at step {step}, {obj} from there", i

    def _set_object(self) -> tuple[str, None]:
        obj = self._object()
        i = self.edits.set_object(self.current_step(), obj)
        return f"subtask {i + 1} is relative to {obj}", None

    def _object(self) -> str:
        value = self.object_dd.value
        if value not in self.choices:
            raise AnnotationError(f"{value!r} is not an object of this scene")
        return value

    def _on_pick_arm(self, event) -> None:
        if event.client_id is None:
            return
        with self._lock:
            try:
                self.edits.select_arm(str(self.arm_dd.value))
            except AnnotationError as exc:
                self.message = f"refused: {exc}"
            else:
                self.message = f"editing the {self.edits.arm} arm's subtasks"
            self._refresh(select=0)
        self.jump(self.current_step())

    def _on_pick_boundary(self, event) -> None:
        if event.client_id is None:  # set by the server itself (after an edit)
            return
        with self._lock:
            if self.boundary_dd.value not in self.boundary_dd.options or not self.edits.boundaries:
                self._refresh()  # dropped: not one of the options
                return
            step = self.edits.boundaries[self._chosen()]
            self.boundary_step.value = step
        self.jump(step)

    def _on_boundary_step(self, event) -> None:
        if event.client_id is None:
            return
        step = step_from_browser(self.boundary_step.value, self.episode.steps)
        if step is None:  # dropped; the field keeps what was typed, the boundary stays
            with self._lock:
                self.message = f"refused: {self.boundary_step.value!r} is not a step of this episode (0-{self.episode.steps - 1})"
                self._refresh(sync_step=False)
            return
        with self._lock:
            try:
                self.edits.move(self._chosen(), step)
            except AnnotationError as exc:
                self.message = f"refused: {exc}"
                moved = False
            else:
                self.message = f"boundary {self._chosen() + 1} moved to step {step}"
                self.state, moved = UNSAVED, True
            self._refresh(sync_step=False)
        if moved:
            self.jump(step)

    def _on_save(self, event) -> None:
        if event.client_id is None:  # only a page's click (past the gate) writes the file
            return
        self.save()

    def save(self) -> None:
        """Write the sidecar file (by "human"); a failure is shown, not raised."""
        with self._lock:
            try:
                path = write_subtasks(self.episode.path, self.edits.all_subtasks, self.episode.steps, by="human")
            except AnnotationError as exc:
                self.message = f"not saved: {exc}"
            except OSError as exc:
                # a full disk: one line naming the file and the cause; the file saved before stays as it was
                self.message = f"not saved: cannot write {sidecar_path(self.episode.path)}: {cause(exc)}"
            else:
                self.state, self.message = f"saved to {path.name}", ""
            self._refresh()
