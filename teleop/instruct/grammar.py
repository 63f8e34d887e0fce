"""A sentence parsed against the scene's objects into atomic actions (the rule planner's first half).

The grammar (case and punctuation do not matter; clauses join with "then", "and", ",", ";"):

  pick up | pick | lift | grab | grasp | take | raise  X [up]
  put | place | set | stack | move | drop | lay  X  on | onto | on top of | in | into | inside | at | to  Y
  push | slide | shove | nudge  X  [forward]  to | onto | into | toward | on  Y
  open | close | release  the gripper | hand
  go | return | move  [back] [to] home

A clause without a verb repeats the previous one's ("the red cube in the red bin and the blue cube
in the blue bin"). An object phrase names an object by its colour (the nearest colour word to the
task file's rgba), its name's words and its shape's words ("the red block", "the blue one", "the
can", "the green square"); "it" is the last object named. A phrase that fits no object, or
more than one, is a GroundingError naming what is missing and what the scene has.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from scenes.errors import TeleopError
from teleop.instruct.perceive import SceneObject

COLOURS = {
    "red": (0.85, 0.2, 0.15), "blue": (0.15, 0.45, 0.85), "green": (0.2, 0.75, 0.3), "yellow": (0.9, 0.8, 0.15),
    "orange": (0.95, 0.55, 0.1), "purple": (0.55, 0.25, 0.7), "pink": (0.95, 0.5, 0.7), "grey": (0.55, 0.57, 0.6),
    "white": (0.95, 0.95, 0.95), "black": (0.1, 0.1, 0.1), "brown": (0.5, 0.32, 0.18),
}
SYNONYMS = {"gray": "grey", "cuboid": "box", "bucket": "bin"}
SHAPE_WORDS = {
    "box": ("cube", "block", "box", "brick"),
    "cylinder": ("cylinder", "can", "peg", "puck"),
    "sphere": ("ball", "sphere"),
    "capsule": ("capsule", "rod", "bar"),
    "bin": ("bin", "box", "container", "tray"),
}
MARK_WORDS = ("square", "target", "mark", "pad", "goal", "area", "spot", "marker", "zone")
ANY_WORDS = ("one", "object", "thing", "item")
SKIP_WORDS = {"the", "a", "an", "this", "that", "other", "shaped", "top", "of", "please", "its", "own", "side"}
ADVERBS = {"forward", "forwards", "gently", "carefully", "slowly", "back", "over", "then", "please", "now"}


class GroundingError(TeleopError, ValueError):
    """A sentence the planner cannot ground in the scene; one line naming what is missing and what the scene has."""


@dataclass(frozen=True)
class Action:
    """One atomic action: pick X, place X on/in Y, push X to Y, open/close the gripper, go home."""

    kind: str  # "pick" | "place" | "push" | "open" | "close" | "home"
    obj: str | None = None
    target: str | None = None
    prep: str = ""  # "on" | "in" for place

    def text(self) -> str:
        if self.kind == "place":
            return f"place {self.obj} {self.prep} {self.target}"
        if self.kind == "push":
            return f"push {self.obj} to {self.target}"
        if self.kind in ("open", "close"):
            return f"{self.kind} gripper"
        return "go home" if self.kind == "home" else f"{self.kind} {self.obj}"


def colour_word(rgba) -> str:
    """The nearest colour word to an rgba (0..1)."""
    c = np.asarray(rgba[:3], float)
    return min(COLOURS, key=lambda k: float(np.linalg.norm(np.asarray(COLOURS[k]) - c)))


def describe(obj: SceneObject) -> str:
    """How the scene's objects are listed in an error: "red cube (cube)"."""
    return f"{colour_word(obj.rgba)} {obj.name.replace('_', ' ')}"


def object_words(obj: SceneObject) -> set[str]:
    words = set(obj.name.lower().split("_")) | set(SHAPE_WORDS.get(obj.shape, ()))
    if obj.fixed and obj.rgba[3] < 0.95 or obj.name in MARK_WORDS:
        words |= set(MARK_WORDS)
    words |= {w[:-1] for w in words if w.endswith("s")}
    return words


VERBS = {
    "pick": ("pick up", "pick", "lift", "grab", "grasp", "take", "raise"),
    "place": ("put", "place", "set", "stack", "move", "drop", "lay", "insert"),
    "push": ("push", "slide", "shove", "nudge"),
}
PLACE_PREP = r"(?P<prep>on top of|onto|on|into|inside|in|at|to|over)"
PUSH_PREP = r"(?P<prep>onto|on|into|toward|towards|to|over)"


class Grounder:
    """Names in a sentence to the scene's objects, remembering the last one for "it" and "one"."""

    def __init__(self, objects: list[SceneObject]) -> None:
        self.objects = objects
        self.last: str | None = None
        self.last_noun: str | None = None

    def scene_text(self) -> str:
        return ", ".join(describe(o) for o in self.objects) or "no objects"

    def ground(self, phrase: str) -> str:
        words = [SYNONYMS.get(w, w) for w in phrase.split() if w not in SKIP_WORDS and w not in ADVERBS]
        if words in (["it"], ["them"]):
            if self.last is None:
                raise GroundingError(f"'{phrase}' refers to nothing named before it (the scene has: {self.scene_text()})")
            return self.last
        colours = [w for w in words if w in COLOURS]
        nouns = [w for w in words if w not in COLOURS]
        nouns = [self.last_noun if w in ANY_WORDS and self.last_noun else w for w in nouns]
        nouns = [w for w in nouns if w not in ANY_WORDS]
        fits = []
        for obj in self.objects:
            have = object_words(obj)
            if colours and colour_word(obj.rgba) not in colours:
                continue
            if all(n in have or n.rstrip("s") in have for n in nouns):
                fits.append(obj)
        if not fits:
            raise GroundingError(f"no {' '.join(words) or phrase} in the scene (it has: {self.scene_text()})")
        if len(fits) > 1:
            movable = [o for o in fits if not o.fixed]  # "the cube" beside a flat square target: the one that moves
            fits = movable if len(movable) == 1 else fits
        if len(fits) > 1:
            raise GroundingError(f"'{phrase}' could be any of {', '.join(describe(o) for o in fits)}: say which by colour or name")
        self.last = fits[0].name
        self.last_noun = nouns[-1] if nouns else self.last_noun
        return fits[0].name


def normalise(sentence: str) -> str:
    text = sentence.lower().replace("-", " ")
    text = re.sub(r"[^a-z0-9,; ]+", " ", text)
    return re.sub(r"\s+", " ", text).strip()


def clauses(sentence: str) -> list[str]:
    parts = re.split(r"\s*(?:,|;|\band then\b|\bthen\b|\band\b)\s*", normalise(sentence))
    return [p.strip() for p in parts if p.strip()]


def parse(sentence: str, objects: list[SceneObject]) -> list[Action]:
    """The sentence's atomic actions over `objects`; GroundingError when it names what is not there."""
    grounder = Grounder(objects)
    actions: list[Action] = []
    verb_of_last = None
    for clause in clauses(sentence):
        clause = " ".join(w for w in clause.split() if w not in ADVERBS)
        found = parse_clause(clause, grounder)
        if found is None and verb_of_last is not None:
            found = parse_clause(f"{verb_of_last} {clause}", grounder)
        if found is None:
            raise GroundingError(f"cannot read '{clause}' (say pick X, put X on/in Y, push X to Y, open/close the gripper, "
                                 f"go home; the scene has: {grounder.scene_text()})")
        verb, new = found
        verb_of_last = verb
        for action in new:
            if action.kind == "pick" and actions and actions[-1] == action:
                continue  # "pick up the cube and lift it": one pick lifts it
            actions.append(action)
    if not actions:
        raise GroundingError(f"an empty instruction (the scene has: {grounder.scene_text()})")
    return actions


def parse_clause(clause: str, g: Grounder) -> tuple[str, list[Action]] | None:
    """(the verb as written, the actions) of one clause, or None when no pattern reads it."""
    if re.fullmatch(r"(?:go|return|move|come)(?: back)?(?: to)?(?: the)? (?:home|start)(?: position)?", clause):
        return "go", [Action("home")]
    m = re.fullmatch(r"(open|close|release)(?: the)? (?:gripper|hand|fingers|claw)", clause)
    if m:
        return m.group(1), [Action("open" if m.group(1) in ("open", "release") else "close")]
    for verb in VERBS["push"]:
        m = re.fullmatch(rf"{verb} (?P<x>.+?) {PUSH_PREP} (?P<y>.+)", clause)
        if m:
            x = g.ground(m.group("x"))
            return verb, [Action("push", x, g.ground(m.group("y")))]
    for verb in VERBS["place"]:
        m = re.fullmatch(rf"{verb} (?P<x>.+?) {PLACE_PREP} (?P<y>.+)", clause)
        if m:
            x = g.ground(m.group("x"))
            prep = "in" if m.group("prep") in ("in", "into", "inside") else "on"
            return verb, [Action("place", x, g.ground(m.group("y")), prep)]
    for verb in VERBS["pick"]:
        m = re.fullmatch(rf"{verb} (?P<x>.+?)(?: up)?", clause)
        if m:
            return verb, [Action("pick", g.ground(m.group("x")))]
    return None
