"""A task file's success expression: tokenised and parsed into a tree, never `eval`'d.

Grammar (see docs/tasks.md, "Tasks as files"):

    expr   := term ("or" term)*
    term   := factor ("and" factor)*
    factor := "not" factor | "(" expr ")" | PRED "(" arg ("," arg)* ")"
    arg    := NAME | NUMBER [UNIT]

NAME may hold letters, digits, `_`, `/` and `-` (a prefixed bimanual name such as
`right/ee_site`). UNIT is one of LENGTH_UNITS or ANGLE_UNITS. Checking a predicate's
argument kinds happens here; checking that names exist happens when the task loads.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from scenes.errors import TeleopError


class ExpressionError(TeleopError):
    """A success expression that does not parse (the message names the problem)."""


LENGTH_UNITS = ("size", "spread", "reach", "m")  # layout units (see scenes.tasks.file_values.length) and metres
ANGLE_UNITS = ("deg", "rad")

# predicate -> the kinds of its arguments: "name" (an object/body/site/geom), "joint", "length", "angle", "amount"
PREDICATES: dict[str, tuple[str, ...]] = {
    "lifted": ("name", "length"),
    "on": ("name", "name"),
    "inside": ("name", "name"),
    "in_region": ("name", "name"),
    "near": ("name", "name", "length"),
    "upright": ("name", "angle"),
    "at_rest": ("name",),
    "open": ("joint", "amount"),
    "closed": ("joint", "amount"),
    "grasped": ("name",),
}


@dataclass(frozen=True)
class Number:
    """A numeric argument: `value` in `unit` ("" for a plain number)."""

    value: float
    unit: str = ""


@dataclass(frozen=True)
class Pred:
    name: str
    args: tuple[str | Number, ...]


@dataclass(frozen=True)
class Not:
    arg: "Node"


@dataclass(frozen=True)
class And:
    args: tuple["Node", ...]


@dataclass(frozen=True)
class Or:
    args: tuple["Node", ...]


Node = Pred | Not | And | Or

_TOKEN = re.compile(r"\s*(?:(?P<num>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)|(?P<name>[A-Za-z_][A-Za-z0-9_/\-]*)|(?P<punct>[(),]))")


def tokenize(text: str) -> list[tuple[str, str]]:
    out, pos = [], 0
    text = text.rstrip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            raise ExpressionError(f"unexpected character {text[pos:].lstrip()[:1]!r} at position {pos}")
        kind = m.lastgroup or ""
        out.append((kind, m.group(kind)))
        pos = m.end()
    return out


class _Parser:
    def __init__(self, text: str) -> None:
        self.tokens = tokenize(text)
        self.i = 0

    def peek(self) -> tuple[str, str] | None:
        return self.tokens[self.i] if self.i < len(self.tokens) else None

    def take(self, value: str | None = None) -> tuple[str, str]:
        tok = self.peek()
        if tok is None:
            raise ExpressionError(f"expression ends early (expected {value or 'more'})")
        if value is not None and tok[1] != value:
            raise ExpressionError(f"expected {value!r}, found {tok[1]!r}")
        self.i += 1
        return tok

    def expr(self) -> Node:
        args = [self.term()]
        while self.peek() == ("name", "or"):
            self.take()
            args.append(self.term())
        return args[0] if len(args) == 1 else Or(tuple(args))

    def term(self) -> Node:
        args = [self.factor()]
        while self.peek() == ("name", "and"):
            self.take()
            args.append(self.factor())
        return args[0] if len(args) == 1 else And(tuple(args))

    def factor(self) -> Node:
        tok = self.take()
        if tok == ("name", "not"):
            return Not(self.factor())
        if tok == ("punct", "("):
            node = self.expr()
            self.take(")")
            return node
        if tok[0] != "name":
            raise ExpressionError(f"expected a predicate, found {tok[1]!r}")
        name = tok[1]
        if name not in PREDICATES:
            raise ExpressionError(f"unknown predicate {name!r} (predicates: {', '.join(PREDICATES)})")
        self.take("(")
        args: list[str | Number] = [self.arg()]
        while self.peek() == ("punct", ","):
            self.take()
            args.append(self.arg())
        self.take(")")
        return _checked(Pred(name, tuple(args)))

    def arg(self) -> str | Number:
        kind, value = self.take()
        if kind == "num":
            unit = ""
            nxt = self.peek()
            if nxt is not None and nxt[0] == "name" and nxt[1] in LENGTH_UNITS + ANGLE_UNITS:
                unit = self.take()[1]
            return Number(float(value), unit)
        if kind == "name":
            return value
        raise ExpressionError(f"expected an argument, found {value!r}")


def _checked(pred: Pred) -> Pred:
    kinds = PREDICATES[pred.name]
    if len(pred.args) != len(kinds):
        raise ExpressionError(f"{pred.name} takes {len(kinds)} argument(s), got {len(pred.args)}")
    for i, (kind, arg) in enumerate(zip(kinds, pred.args), 1):
        numeric = kind in ("length", "angle", "amount")
        if numeric != isinstance(arg, Number):
            want = "a number" if numeric else "a name"
            raise ExpressionError(f"{pred.name}: argument {i} must be {want}")
        if isinstance(arg, Number):
            if kind == "length" and arg.unit not in ("",) + LENGTH_UNITS:
                raise ExpressionError(f"{pred.name}: argument {i} is a length; unit {arg.unit!r} is not one ({', '.join(LENGTH_UNITS)})")
            if kind == "angle" and arg.unit not in ("",) + ANGLE_UNITS:
                raise ExpressionError(f"{pred.name}: argument {i} is an angle; unit {arg.unit!r} is not one ({', '.join(ANGLE_UNITS)})")
    return pred


def parse(text: str) -> Node:
    """The tree of a success expression; ExpressionError (one line) if it does not parse."""
    parser = _Parser(text)
    if not parser.tokens:
        raise ExpressionError("empty expression")
    node = parser.expr()
    if parser.peek() is not None:
        raise ExpressionError(f"unexpected {parser.peek()[1]!r} after a complete expression")
    return node


def predicates(node: Node) -> list[Pred]:
    """Every predicate in the tree, in order."""
    if isinstance(node, Pred):
        return [node]
    if isinstance(node, Not):
        return predicates(node.arg)
    return [p for a in node.args for p in predicates(a)]
