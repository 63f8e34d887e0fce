"""Subtask annotations: where an episode's object-centric subtasks begin and end.

Generation (MimicGen's method) splits a demonstration into subtasks, each
relative to one reference object (grasp the cube, then place it on the base).
The boundaries are stored beside the episode in a sidecar file, so annotating
never rewrites a recorded step (and a crash-safe MCAP file stays untouched):

    episode_000003.mcap
    episode_000003.mcap.subtasks.json   {"version": 1, "steps": 142, "by": "auto",
                                         "subtasks": [{"object": "cube", "start": 0, "end": 61}, ...]}

Steps are control ticks of the episode: `start` inclusive, `end` exclusive.
The subtasks are contiguous and cover the episode: the first starts at 0, each
next one starts where the previous ended, the last ends at the episode's steps.

A two-arm task is annotated per arm: each subtask then carries its `arm` ("left",
"right"), the list holds one arm's subtasks after the other's, and each arm's own
subtasks are contiguous and cover the episode. A one-arm file has no `arm` keys.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from recorder.disk import write_text_whole
from scenes.errors import TeleopError

SIDECAR_SUFFIX = ".subtasks.json"
VERSION = 1


class AnnotationError(TeleopError, ValueError):
    """Boundaries that do not describe the episode (the message names the file)."""


@dataclass(frozen=True)
class Subtask:
    """One segment of an episode, relative to one reference object (a body, site or geom name)."""

    object: str
    start: int  # first step (inclusive)
    end: int  # last step + 1
    arm: str = ""  # the arm whose subtask it is (a two-arm task); "" the only arm

    def to_json(self) -> dict:
        out = {"object": self.object, "start": int(self.start), "end": int(self.end)}
        return {**out, "arm": self.arm} if self.arm else out


def by_arm(subtasks: Sequence[Subtask]) -> dict[str, list[Subtask]]:
    """Each arm's subtasks in order ("" the only arm of a one-arm annotation)."""
    out: dict[str, list[Subtask]] = {}
    for s in subtasks:
        out.setdefault(s.arm, []).append(s)
    return out


def sidecar_path(episode: str | Path) -> Path:
    """Where an episode file's annotations live: the file's name plus SIDECAR_SUFFIX."""
    episode = Path(episode)
    return episode.with_name(episode.name + SIDECAR_SUFFIX)


def check_subtasks(subtasks: Sequence[Subtask], steps: int, where: str = "annotations") -> None:
    """Raise AnnotationError unless the subtasks (each arm's, for a two-arm task) are contiguous and cover 0..steps."""
    if not subtasks:
        raise AnnotationError(f"{where}: no subtasks")
    groups = by_arm(subtasks)
    if len(groups) > 1:
        if "" in groups:
            raise AnnotationError(f"{where}: some subtasks name an arm and some do not")
        order = [s.arm for s in subtasks]
        if order != sorted(order, key=list(groups).index):
            raise AnnotationError(f"{where}: one arm's subtasks, then the next arm's (not interleaved)")
        for arm, group in groups.items():
            check_subtasks(group, steps, f"{where} ({arm} arm)")
        return
    expected = 0
    for i, s in enumerate(subtasks):
        if not s.object:
            raise AnnotationError(f"{where}: subtask {i} names no object")
        if s.start != expected:
            raise AnnotationError(f"{where}: subtask {i} starts at step {s.start}, expected {expected} (no gaps or overlaps)")
        if s.end <= s.start:
            raise AnnotationError(f"{where}: subtask {i} ends at step {s.end}, not after its start {s.start}")
        expected = s.end
    if expected != steps:
        raise AnnotationError(f"{where}: the last subtask ends at step {expected}, the episode has {steps} steps")


def from_boundaries(objects: Sequence[str], ends: Sequence[int], steps: int, arm: str = "") -> list[Subtask]:
    """Subtasks (of `arm`) from their objects and the end step of all but the last (which ends at `steps`)."""
    if len(ends) != len(objects) - 1:
        raise AnnotationError(f"{len(objects)} subtasks need {len(objects) - 1} boundaries, got {len(ends)}")
    bounds = [0, *(int(e) for e in ends), int(steps)]
    return [Subtask(obj, bounds[i], bounds[i + 1], arm) for i, obj in enumerate(objects)]


def write_subtasks(episode: str | Path, subtasks: Sequence[Subtask], steps: int, by: str = "human") -> Path:
    """Check and store the annotations of `episode` (atomically: a crash leaves the old file or the new)."""
    path = sidecar_path(episode)
    check_subtasks(subtasks, steps, str(path))
    doc = {"version": VERSION, "episode": Path(episode).name, "steps": int(steps), "by": by,
           "subtasks": [s.to_json() for s in subtasks]}
    return write_text_whole(path, json.dumps(doc, indent=1) + "\n")  # a full disk: WriteError, no .part left


def read_subtasks(episode: str | Path, steps: int | None = None) -> list[Subtask] | None:
    """The stored annotations of `episode`, or None when it has none.

    With `steps` given, annotations made for a different length (the file was
    recovered or rewritten since) are an error rather than silently wrong.
    """
    path = sidecar_path(episode)
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        subtasks = [Subtask(str(s["object"]), int(s["start"]), int(s["end"]), str(s.get("arm", ""))) for s in doc["subtasks"]]
        recorded_steps = int(doc.get("steps", subtasks[-1].end if subtasks else 0))
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise AnnotationError(f"{path}: not a subtask annotation file ({type(exc).__name__}: {exc})") from None
    if steps is not None and recorded_steps != steps:
        raise AnnotationError(f"{path}: made for {recorded_steps} steps, the episode has {steps}; annotate it again")
    check_subtasks(subtasks, recorded_steps, str(path))
    return subtasks
