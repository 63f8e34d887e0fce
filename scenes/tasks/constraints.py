"""Two-arm tasks: which arm each subtask belongs to, and the `[[constraint]]`s between the arms' subtasks.

Each arm has its own sequence of object-centric subtasks (a subtask's `arm`), run in
parallel by generation unless a constraint ties them (DexMimicGen's and Isaac Lab
Mimic's subtask constraints, from our reading of them):

    [[constraint]]
    kind = "sequential"          # the right arm's subtask 1 starts only after the left arm's subtask 0 ends
    first = ["left", 0]
    then = ["right", 1]

    [[constraint]]
    kind = "coordinated"         # one source episode and one transform for both; they end on the same tick
    subtasks = [["left", 1], ["right", 1]]

A subtask is named (arm, index among that arm's subtasks). The checks at load: the arm
exists, the index is in range, and the constraints with each arm's own order (subtask i
before i + 1) leave no cycle (a schedule that would wait forever); each is one line.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from scenes.tasks.base import SubtaskSpec
from scenes.tasks.file_values import TaskFileError

TWO_ARMS = ("left", "right")  # the bimanual robot's arms, by the name prefix of their sites
CONSTRAINT_KINDS = ("sequential", "coordinated")

Ref = tuple[str, int]  # (arm, index among that arm's subtasks)


@dataclass(frozen=True)
class Constraint:
    """One `[[constraint]]`: sequential (`refs` = (first, then)) or coordinated (`refs` = the subtasks run together)."""

    kind: str
    refs: tuple[Ref, ...]

    def to_json(self) -> dict:
        if self.kind == "sequential":
            return {"kind": self.kind, "first": list(self.refs[0]), "then": list(self.refs[1])}
        return {"kind": self.kind, "subtasks": [list(r) for r in self.refs]}


def per_arm(specs: Sequence[SubtaskSpec]) -> dict[str, list[SubtaskSpec]]:
    """The subtasks of each arm in order ("" is the only arm of a one-arm task)."""
    out: dict[str, list[SubtaskSpec]] = {}
    for spec in specs:
        out.setdefault(spec.arm, []).append(spec)
    return out


def check_arms(specs: Sequence[SubtaskSpec], arms: Sequence[str], where: str) -> None:
    """Every subtask's `arm` is one of `arms` (a one-arm task: none), given for all subtasks or none."""
    named = [s.arm for s in specs if s.arm]
    for i, spec in enumerate(specs):
        if spec.arm and spec.arm not in arms:
            hint = f"arms: {', '.join(arms)}" if len(arms) > 1 else "a one-arm task's subtasks take no arm"
            raise TaskFileError(f"{where}: subtasks[{i}]: arm: {spec.arm!r} is not an arm of this task ({hint})")
    if named and len(named) != len(specs):
        i = next(i for i, s in enumerate(specs) if not s.arm)
        raise TaskFileError(f"{where}: subtasks[{i}]: arm: missing (give every subtask an arm, or none)")


def _ref(value: Any, counts: dict[str, int], w: str) -> Ref:
    if not (isinstance(value, list) and len(value) == 2 and isinstance(value[0], str)
            and isinstance(value[1], int) and not isinstance(value[1], bool)):
        raise TaskFileError(f"{w}: expected [\"arm\", subtask index], got {value!r}")
    arm, index = value[0], value[1]
    if arm not in counts:
        known = ", ".join(a for a in counts if a) or "none: the subtasks name no arm"
        raise TaskFileError(f"{w}: {arm!r} is not an arm with subtasks in this task (arms: {known})")
    if not 0 <= index < counts[arm]:
        raise TaskFileError(f"{w}: subtask {index} is out of range (the {arm} arm has {counts[arm]} subtasks)")
    return arm, index


def read_constraints(entries: Any, specs: Sequence[SubtaskSpec], where: str) -> tuple[Constraint, ...]:
    """The `[[constraint]]` tables, checked against the subtasks of each arm (TaskFileError, one line)."""
    if not isinstance(entries, list):
        raise TaskFileError(f"{where}: constraint: use [[constraint]] tables")
    counts = {arm: len(subs) for arm, subs in per_arm(specs).items()}
    out: list[Constraint] = []
    for i, entry in enumerate(entries):
        w = f"{where}: [[constraint]] {i}"
        if not isinstance(entry, dict):
            raise TaskFileError(f"{w}: expected a table")
        kind = entry.get("kind")
        if kind not in CONSTRAINT_KINDS:
            raise TaskFileError(f"{w}: kind: expected one of {', '.join(CONSTRAINT_KINDS)}, got {kind!r}")
        fields = {"kind", "first", "then"} if kind == "sequential" else {"kind", "subtasks"}
        unknown = sorted(set(entry) - fields)
        missing = sorted(fields - set(entry))
        if unknown or missing:
            bad = f"unknown field '{unknown[0]}'" if unknown else f"{missing[0]}: missing"
            raise TaskFileError(f"{w}: {bad} (a {kind} constraint takes {', '.join(sorted(fields - {'kind'}))})")
        if kind == "sequential":
            refs = (_ref(entry["first"], counts, f"{w}: first"), _ref(entry["then"], counts, f"{w}: then"))
            if refs[0][0] == refs[1][0]:
                raise TaskFileError(f"{w}: first and then are on the same arm ({refs[0][0]}): its own order already holds")
        else:
            group = entry["subtasks"]
            if not isinstance(group, list) or len(group) < 2:
                raise TaskFileError(f"{w}: subtasks: expected two or more [\"arm\", index] pairs")
            refs = tuple(_ref(r, counts, f"{w}: subtasks[{k}]") for k, r in enumerate(group))
            arms = [r[0] for r in refs]
            if len(set(arms)) != len(arms):
                raise TaskFileError(f"{w}: subtasks: one subtask per arm (the {arms[0]} arm is named twice)")
        out.append(Constraint(kind, refs))
    check_no_cycle(out, counts, where)
    return tuple(out)


def check_no_cycle(constraints: Sequence[Constraint], counts: dict[str, int], where: str) -> None:
    """Refuse constraints that can never all hold: a cycle through each arm's own order and the
    sequential constraints, with coordinated subtasks taken as one (they start together)."""
    node: dict[Ref, Ref] = {(a, i): (a, i) for a, n in counts.items() for i in range(n)}
    for c in constraints:
        if c.kind == "coordinated":
            root = node[c.refs[0]]
            for r in c.refs[1:]:
                old = node[r]
                for k, v in node.items():
                    if v == old:
                        node[k] = root
    edges: dict[Ref, set[Ref]] = {}
    for a, n in counts.items():
        for i in range(n - 1):
            edges.setdefault(node[(a, i)], set()).add(node[(a, i + 1)])
    for c in constraints:
        if c.kind == "sequential":
            edges.setdefault(node[c.refs[0]], set()).add(node[c.refs[1]])
    state: dict[Ref, int] = {}  # 1: on the path, 2: done

    def visit(n: Ref, path: list[Ref]) -> None:
        state[n] = 1
        for m in sorted(edges.get(n, ())):
            if state.get(m) == 1 or m == n:
                loop = path[path.index(m):] + [m] if m in path else [n, m]
                text = " -> ".join(f"{a} {i}" for a, i in loop)
                raise TaskFileError(f"{where}: constraint: the subtasks wait on each other in a cycle ({text})")
            if m not in state:
                visit(m, path + [m])
        state[n] = 2

    for n in sorted(set(node.values())):
        if n not in state:
            visit(n, [n])
