"""The import graph is a DAG with the app on top, checked on the source with `ast`.

scenes/ imports none of our folders; devices/ and recorder/ at most scenes/;
replay/ at most recorder/ and scenes/; teleop/ may import all. An import inside
a function counts like any other: hiding one there does not get around the rule.
Inside teleop/ and replay/ the parts have layers of their own (TELEOP_ALLOWED,
REPLAY_ALLOWED); the process pool (scenes/workers/) needs only the root error; no module
imports itself back at module level (TYPE_CHECKING imports count); and no module
takes another's private (`_name`) names. Kept on purpose (issue 19): one error
root, and one loop (`run_episode`) around Session.step. Each check has a self-test
that shows it can fail.
"""

from __future__ import annotations

import ast
import importlib.util
from functools import lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
ALLOWED: dict[str, set[str]] = {
    "scenes": set(),
    "devices": {"scenes"},
    "recorder": {"scenes"},
    "replay": {"recorder", "scenes"},
    "teleop": {"scenes", "devices", "recorder", "replay"},
}
OURS = set(ALLOWED) | {"bench", "tests"}


@lru_cache(maxsize=None)
def parse_text(text: str, filename: str) -> ast.Module:
    """A file's syntax tree, parsed once per content: every check here walks the same few hundred files."""
    return ast.parse(text, filename=filename)


def parsed(path: Path) -> ast.Module:
    return parse_text(path.read_text(), str(path))


def imported_modules(path: Path) -> list[tuple[int, str, bool]]:
    """(line, module, inside a function) for every absolute import in a file."""
    return [(line, module, in_function) for line, module, _, in_function in imports_with_names(path)]


@lru_cache(maxsize=None)
def edges() -> tuple[tuple[str, int, str, str, bool], ...]:
    """(file, line, its package, imported module, inside a function) for every import of ours: walked once per
    process for all the checks that read it."""
    out = []
    for package in ALLOWED:
        for path in sorted((ROOT / package).rglob("*.py")):
            for line, module, in_function in imported_modules(path):
                out.append((str(path.relative_to(ROOT)), line, package, module, in_function))
    return tuple(out)


def test_the_walker_sees_imports_at_every_level(tmp_path):
    sample = tmp_path / "sample.py"
    sample.write_text("import os\nfrom replay import episode\n\ndef f():\n    from teleop import session\n")
    assert [(m, f) for _, m, f in imported_modules(sample)] == [("os", False), ("replay", False), ("teleop", True)]


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_imports_follow_the_layers(package):
    bad = [
        f"{path}:{line} imports {module}"
        for path, line, pkg, module, _ in edges()
        if pkg == package and (top := module.split(".")[0]) in OURS and top != pkg and top not in ALLOWED[pkg]
    ]
    assert not bad, f"{package}/ may import only {sorted(ALLOWED[package]) or 'none of ours'}:\n" + "\n".join(bad)


def test_the_library_layers_import_none_of_ours_lazily():
    """Below the app, an import inside a function is kept for optional heavy dependencies only."""
    lazy = [
        f"{path}:{line} imports {module} inside a function"
        for path, line, pkg, module, in_function in edges()
        if in_function and pkg != "teleop" and module.split(".")[0] in OURS and module.split(".")[0] != pkg
    ]
    assert not lazy, "\n".join(lazy)


# -- inside teleop/: the app's own layers ------------------------------------------
# A part of teleop/ is a sub-package (control, generate, learn, web, campaign, cli) or a top module
# (errors, gym: the public `teleop.gym`, __init__: the public `import teleop`, __main__).
# The data flows control -> generate / learn -> web -> campaign -> cli: a part imports only the parts
# its row names, and only cli/ (the commands) imports every part.
TELEOP_PARTS = ("errors", "control", "generate", "learn", "web", "campaign", "gym", "__init__", "lerobot_plugin", "instruct",
                "cli", "__main__")
TELEOP_ALLOWED: dict[str, set[str]] = {
    "errors": set(),                                 # the teleop errors, on scenes.errors' root
    "control": {"errors"},                           # controller, IK, session, loop, recording
    "generate": {"errors", "control"},               # scripted demonstrations at scale
    "learn": {"errors", "control"},                  # policy, evaluate, Gymnasium env, takeover
    "web": {"errors", "control", "learn"},           # the browser session (a policy may drive it)
    "campaign": {"errors", "control", "web"},        # many operators, a session process each (issue 35)
    "gym": {"learn"},                                # `teleop.gym`: registers learn/'s environment
    "__init__": {"errors", "control", "web"},        # `import teleop`: the scripting API
    "lerobot_plugin": {"errors", "control", "learn", "web"},  # LeRobot's robot, teleoperator and env types (issue 58)
    "instruct": set(),                               # a camera finds the objects, a sentence becomes a plan (issue 59)
    "cli": set(TELEOP_PARTS) - {"cli", "__main__"},  # the commands: every part
    "__main__": {"cli"},                             # `python -m teleop`
}


def module_name(root: Path, path: Path) -> str:
    """`teleop/control/session.py` -> `teleop.control.session`; a package's `__init__.py` -> the package."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_with_names(path: Path) -> list[tuple[int, str, tuple[str, ...], bool]]:
    """(line, module, names a `from` import takes, inside a function) for every absolute import.

    An import under `if TYPE_CHECKING:` is at module level here: the annotations it serves
    tie the two modules together all the same.
    """
    tree = parsed(path)
    found: list[tuple[int, str, tuple[str, ...], bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            nested = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                found.extend((child.lineno, alias.name, (), in_function) for alias in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                found.append((child.lineno, child.module, tuple(a.name for a in child.names), in_function))
            visit(child, nested)

    visit(tree, False)
    return found


def module_graph(root: Path, packages, module_level_only: bool) -> dict[str, dict[str, str]]:
    """module -> {module of ours it imports: "path:line"}. `from pkg import mod` names the module
    pkg.mod; importing a.b.c is not counted as importing its parents a and a.b (Python runs them
    first, but a package that re-exports its modules would otherwise sit in a cycle with each)."""
    files = {module_name(root, p): p for package in packages for p in sorted((root / package).rglob("*.py"))}

    def ours(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, dict[str, str]] = {}
    for module, path in files.items():
        targets = graph.setdefault(module, {})
        for line, imported, names, in_function in imports_with_names(path):
            if in_function and module_level_only:
                continue
            for target in [f"{imported}.{n}" if f"{imported}.{n}" in files else imported for n in names] or [imported]:
                if (found := ours(target)) is not None and found != module:
                    targets.setdefault(found, f"{path.relative_to(root)}:{line}")
    return graph


def teleop_part(module: str) -> str:
    """teleop.control.session -> control; teleop.gym -> gym; teleop -> __init__."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def layer_violations(root: Path, package: str, allowed: dict[str, set[str]]) -> list[str]:
    """Every import (inside functions too) from one part of `package` into a part its row in `allowed` does not allow."""
    graph = module_graph(root, [package], module_level_only=False)
    return [
        f"{where}: {package}/{teleop_part(module)} imports {target}"
        for module, targets in graph.items()
        for target, where in targets.items()
        if target.split(".")[0] == package and (a := teleop_part(module)) != (b := teleop_part(target))
        and b not in allowed.get(a, set())
    ]


def teleop_layer_violations(root: Path) -> list[str]:
    """Every import (inside functions too) from one part of teleop/ into a part its row does not allow."""
    return layer_violations(root, "teleop", TELEOP_ALLOWED)


def test_the_teleop_table_names_every_part():
    found = {teleop_part(module_name(ROOT, p)) for p in (ROOT / "teleop").rglob("*.py")}
    assert found == set(TELEOP_ALLOWED) == set(TELEOP_PARTS), "add the new part of teleop/ to TELEOP_ALLOWED"


def test_the_teleop_layer_check_can_fail(tmp_path):
    files = {
        "__init__.py": "", "errors.py": "", "control/__init__.py": "", "cli/__init__.py": "",
        "control/session.py": "from teleop.errors import E\n",
        "control/tick.py": "def f():\n    from teleop.cli import entry\n",
        "cli/entry.py": "from teleop.control import session\n",
    }
    for name, text in files.items():
        (tmp_path / "teleop" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "teleop" / name).write_text(text)
    assert teleop_layer_violations(tmp_path) == ["teleop/control/tick.py:2: teleop/control imports teleop.cli.entry"]


def test_the_parts_of_teleop_follow_their_layers():
    bad = teleop_layer_violations(ROOT)
    rows = "\n".join(f"  {part} may import {sorted(allowed) or 'no other part'}"
                     for part, allowed in TELEOP_ALLOWED.items())
    assert not bad, "\n".join(bad) + "\nthe layers inside teleop/:\n" + rows


# -- inside replay/: one reading API, one schema, subtasks in one place ------------------
# A part of replay/ is a sub-package (subtasks, export, review) or a top module. episode.py
# is the one API that reads episode files (with the MCAP reader under it); features.py, the
# frame's schema, sits on it below both the export and teleop/learn; subtasks/ reads episodes
# and is read by the inspect summary; the export takes neither subtasks nor review.
REPLAY_ALLOWED: dict[str, set[str]] = {
    "errors": set(),                                          # the one-line error helpers
    "mcap_read": set(),                                       # MCAP records, crash-cut files too
    "episode": {"errors", "mcap_read"},                       # the reading API: load_episode, Episode, EpisodeMeta
    "convert": {"errors", "episode", "mcap_read"},            # MCAP <-> HDF5, recovery
    "engine": {"errors", "episode"},                          # exact replay and resimulation
    "judge": {"errors", "episode"},                           # success judged on recorded states
    "render": {"errors"},                                     # offscreen rendering
    "render_pool": {"render"},                                # GL contexts kept warm across episodes
    "handoff": set(),                                         # queues between threads that may be told to stop
    "features": {"errors", "episode"},                        # the observation and action schema
    "subtasks": {"errors", "episode"},                        # sidecar files, auto-annotation, hand edits
    "summary": {"episode", "subtasks", "review"},             # what `teleop inspect` shows (quality flags too)
    "export": {"errors", "episode", "engine", "render", "handoff", "features", "review", "subtasks"},  # LeRobot datasets (what passed review)
    "review": {"errors", "episode", "engine", "judge", "render", "render_pool", "handoff", "features", "subtasks"},  # reviewing episodes
    "__init__": {"engine", "episode"},                        # `import replay`
}


def test_the_replay_table_names_every_part():
    found = {teleop_part(module_name(ROOT, p)) for p in (ROOT / "replay").rglob("*.py")}
    assert found == set(REPLAY_ALLOWED), "add the new part of replay/ to REPLAY_ALLOWED"


def test_the_replay_layer_check_can_fail(tmp_path):
    files = {"__init__.py": "", "episode.py": "", "export/__init__.py": "",
             "features.py": "from replay.episode import Episode\nfrom replay.export import options\n",
             "export/options.py": "from replay.features import features\n"}
    for name, text in files.items():
        (tmp_path / "replay" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "replay" / name).write_text(text)
    assert layer_violations(tmp_path, "replay", REPLAY_ALLOWED) == [
        "replay/features.py:2: replay/features imports replay.export.options"]


def test_the_parts_of_replay_follow_their_layers():
    bad = layer_violations(ROOT, "replay", REPLAY_ALLOWED)
    rows = "\n".join(f"  {part} may import {sorted(allowed) or 'no other part'}"
                     for part, allowed in REPLAY_ALLOWED.items())
    assert not bad, "\n".join(bad) + "\nthe layers inside replay/:\n" + rows


FORMAT_READERS = {"replay.episode", "replay.convert", "teleop.control.recording"}  # and recorder/ itself


def format_importers(root: Path, packages) -> dict[str, str]:
    """module -> "path:line" for each module outside recorder/ that imports recorder.format (the file layout)."""
    graph = module_graph(root, packages, module_level_only=False)
    return {module: targets["recorder.format"] for module, targets in graph.items()
            if "recorder.format" in targets and module.split(".")[0] != "recorder"}


def test_the_format_importer_check_can_fail(tmp_path):
    for name, text in {"recorder/__init__.py": "", "recorder/format.py": "", "replay/__init__.py": "",
                       "replay/features.py": "def f():\n    from recorder import format\n"}.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert format_importers(tmp_path, ["recorder", "replay"]) == {"replay.features": "replay/features.py:2"}


def test_readers_use_the_one_reading_api():
    """Learning, generation, export and subtasks read episodes through replay.episode, which re-exports the
    metadata types: only the writer (teleop/control/recording.py) and the two readers take recorder.format."""
    found = format_importers(ROOT, sorted(ALLOWED))
    extra = sorted(f"{where}: {module} imports recorder.format" for module, where in found.items()
                   if module not in FORMAT_READERS)
    assert not extra, "read through replay.episode (EpisodeMeta, ArmMeta, CONTROL_*) instead:\n" + "\n".join(extra)


def test_learning_and_generation_take_the_schema_not_the_export():
    """teleop/learn and teleop/generate share replay.features with the export and import nothing of replay.export."""
    graph = module_graph(ROOT, ["teleop"], module_level_only=False)
    found = sorted(f"{where}: {module} imports {target}" for module, targets in graph.items()
                   if teleop_part(module) in ("learn", "generate")
                   for target, where in targets.items() if target.startswith("replay.export"))
    assert not found, "\n".join(found)


def test_the_process_pool_needs_only_the_root_error():
    """scenes/workers/ (the pool generation, export and the web session share) stays on the lowest floor:
    of ours it imports scenes.errors only, so any folder may use it."""
    graph = module_graph(ROOT, ["scenes"], module_level_only=False)
    found = sorted(f"{where}: {module} imports {target}" for module, targets in graph.items()
                   if module.startswith("scenes.workers")
                   for target, where in targets.items()
                   if not target.startswith("scenes.workers") and target != "scenes.errors")
    assert graph.get("scenes.workers.runner"), "the pool is not where this test looks (scenes/workers/)"
    assert not found, "\n".join(found)


# -- no import cycles ---------------------------------------------------------------


def find_cycle(graph: dict[str, dict[str, str]]) -> list[str]:
    """One cycle in the graph as [a, b, ..., a] (a depth-first search), or [] if it has none."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, {})):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return []

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return []


def test_the_cycle_finder_finds_one_under_type_checking(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("from pkg.b import B\n")
    (tmp_path / "pkg" / "b.py").write_text("import typing\nif typing.TYPE_CHECKING:\n    from pkg import a\n")
    (tmp_path / "pkg" / "c.py").write_text("def f():\n    from pkg import a\n")  # inside a function: not a cycle
    graph = module_graph(tmp_path, ["pkg"], module_level_only=True)
    assert find_cycle(graph) == ["pkg.a", "pkg.b", "pkg.a"]
    del graph["pkg.b"]["pkg.a"]
    assert find_cycle(graph) == []


def test_no_import_cycles():
    """At module level (TYPE_CHECKING imports included), no module of ours comes back to itself."""
    graph = module_graph(ROOT, sorted(ALLOWED), module_level_only=True)
    cycle = find_cycle(graph)
    steps = [f"  {a} -> {b}   ({graph[a][b]})" for a, b in zip(cycle, cycle[1:])]
    assert not cycle, "an import cycle:\n" + "\n".join(steps)


# -- no private names across modules -----------------------------------------------


def private_names_taken(root: Path, packages) -> list[str]:
    """`from mod import _name` and `mod._name`, where mod is one of our modules other than the file's own.

    A `_name` used by another module is an interface: it gets a public name, or the code moves.
    """
    files = {module_name(root, p): p for package in packages for p in sorted((root / package).rglob("*.py"))}
    ours = {m.split(".")[0] for m in files} | set(ALLOWED)

    def private(name: str) -> bool:
        return name.startswith("_") and not name.startswith("__")

    found = []
    for module, path in files.items():
        where = path.relative_to(root)
        tree = parsed(path)
        bound: dict[str, str] = {}  # a local name -> the module of ours it is
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in ours:
                        bound[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] in ours:
                for a in node.names:
                    if f"{node.module}.{a.name}" in files:
                        bound[a.asname or a.name] = f"{node.module}.{a.name}"
                    elif private(a.name) and node.module != module:
                        found.append(f"{where}:{node.lineno}: from {node.module} import {a.name}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and private(node.attr):
                chain, value = [], node.value
                while isinstance(value, ast.Attribute):
                    chain.insert(0, value.attr)
                    value = value.value
                if isinstance(value, ast.Name) and value.id in bound:
                    target = ".".join([bound[value.id], *chain])
                    if target != module:
                        found.append(f"{where}:{node.lineno}: {value.id}{''.join('.' + c for c in chain)}.{node.attr}")
    return found


def test_the_private_name_check_can_fail(tmp_path):
    (tmp_path / "replay").mkdir()
    (tmp_path / "replay" / "__init__.py").write_text("")
    (tmp_path / "replay" / "a.py").write_text("def _helper(): ...\n\n\ndef public(): return _helper()\n")
    (tmp_path / "replay" / "b.py").write_text(
        "from replay.a import __doc__, _helper\nimport replay.a as a\n\na._helper()\na.public()\n")
    assert private_names_taken(tmp_path, ["replay"]) == [
        "replay/b.py:1: from replay.a import _helper", "replay/b.py:4: a._helper"]


def test_no_private_names_taken_across_modules():
    """tests/ and bench/ too: what a test needs of a module is its interface (monkeypatch by string if you must)."""
    found = private_names_taken(ROOT, sorted(OURS))
    assert not found, "a private name used by another module: make it public or move the code:\n" + "\n".join(found)


# -- what is kept (issue 19, item 8): one error root, one loop ---------------------


def errors_off_the_root(root: Path, packages) -> list[str]:
    """Classes named `...Error` whose bases (followed by name through our files) never reach TeleopError."""
    bases: dict[str, list[str]] = {}
    where: dict[str, str] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            for node in ast.walk(parsed(path)):
                if isinstance(node, ast.ClassDef):
                    bases[node.name] = [ast.unparse(b).rpartition(".")[2] for b in node.bases]
                    where[node.name] = f"{path.relative_to(root)}:{node.lineno}"

    def rooted(name: str, seen: frozenset = frozenset()) -> bool:
        return name == "TeleopError" or any(rooted(b, seen | {name}) for b in bases.get(name, []) if b not in seen)

    return [f"{where[name]}: {name}({', '.join(bases[name])})" for name in bases
            if name.endswith("Error") and not rooted(name)]


def test_the_error_root_check_can_fail(tmp_path):
    (tmp_path / "replay").mkdir()
    (tmp_path / "replay" / "a.py").write_text(
        "from scenes.errors import TeleopError\n\nclass EpisodeError(TeleopError): ...\n"
        "class CutShortError(EpisodeError): ...\nclass LostError(RuntimeError): ...\n")
    assert errors_off_the_root(tmp_path, ["replay"]) == ["replay/a.py:5: LostError(RuntimeError)"]


def test_every_error_a_user_can_cause_has_the_one_root():
    """One error root with one-line messages: the CLI prints any TeleopError as a line and exits 2."""
    found = errors_off_the_root(ROOT, sorted(ALLOWED))
    assert not found, "derive these from scenes.errors.TeleopError (or a subclass):\n" + "\n".join(found)


def loops_that_step_a_session(path: Path) -> list[int]:
    """Lines of `for` / `while` loops whose body calls `<...session>.step(...)`."""
    lines = []
    for node in ast.walk(parsed(path)):
        if isinstance(node, (ast.For, ast.While)) and any(
            isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute) and call.func.attr == "step"
            and ast.unparse(call.func.value).endswith("session")
            for statement in node.body for call in ast.walk(statement)
        ):
            lines.append(node.lineno)
    return lines


def test_the_session_loop_check_can_fail(tmp_path):
    sample = tmp_path / "sample.py"
    sample.write_text("def f(self, session):\n    session.step([])\n    while True:\n        self.session.step([])\n"
                      "    for env in envs:\n        env.step(0)\n")
    assert loops_that_step_a_session(sample) == [3]


def test_every_loop_is_run_episode():
    """The CLI, the browser session and generation all tick through teleop.control.loop.run_episode."""
    found = [
        f"{path.relative_to(ROOT)}:{line}"
        for path in sorted((ROOT / "teleop").rglob("*.py"))
        if path != ROOT / "teleop" / "control" / "loop.py"
        for line in loops_that_step_a_session(path)
    ]
    assert not found, "a loop of its own around Session.step: use teleop.control.loop.run_episode:\n" + "\n".join(found)


def test_episode_metadata_keys_are_read_only_in_the_format_module():
    """Outside recorder/format.py nobody looks metadata up by string key."""
    offenders = []
    for package in ALLOWED:
        for path in sorted((ROOT / package).rglob("*.py")):
            if path == ROOT / "recorder" / "format.py":
                continue
            for i, line in enumerate(path.read_text().splitlines(), start=1):
                if "meta[\"" in line or "meta.get(" in line or "meta['" in line:
                    offenders.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_every_device_speaks_the_one_protocol(tmp_path):
    """Devices are typed: the protocol and the capabilities are checked with isinstance, not hasattr."""
    from devices.base import Device, InputStamped, Restartable, SpeedControlled
    from devices.gizmo import GizmoDevice
    from devices.keyboard import KeyboardDevice
    from devices.script import ScriptDevice
    from devices.spacemouse import SpaceMouseDevice
    from teleop.web.session_page.panel import PanelDevice

    script = tmp_path / "s.json"
    script.write_text('{"steps": [{"duration": 0.1}]}')
    devices = [GizmoDevice(), KeyboardDevice(), ScriptDevice(script), SpaceMouseDevice(lambda: None), PanelDevice()]
    assert all(isinstance(d, Device) for d in devices)
    assert [isinstance(d, Restartable) for d in devices] == [False, False, True, False, False]
    assert [isinstance(d, SpeedControlled) for d in devices] == [False, True, False, True, False]
    assert isinstance(devices[0], InputStamped) and not isinstance(devices[1], InputStamped)
    hasattr_checks = [
        f"{path.relative_to(ROOT)}:{i}"
        for path in (ROOT / "teleop").rglob("*.py")
        for i, line in enumerate(path.read_text().splitlines(), start=1)
        if "hasattr(d" in line or "hasattr(device" in line
    ]
    assert not hasattr_checks


def signal_handler_calls(path: Path) -> list[int]:
    """Lines that install a signal handler: `signal.signal(...)`, or `signal` imported from the signal module."""
    lines = []
    for node in ast.walk(parsed(path)):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "signal" \
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "signal":
            lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and node.module == "signal" and any(a.name == "signal" for a in node.names):
            lines.append(node.lineno)
    return lines


def test_only_the_command_line_installs_signal_handlers(tmp_path):
    """Issue 19: library code takes a cancellation token or lets KeyboardInterrupt through; handlers are teleop/cli/'s."""
    sample = tmp_path / "sample.py"
    sample.write_text("import signal\nfrom signal import signal as s\n\ndef f():\n    signal.signal(2, None)\n")
    assert signal_handler_calls(sample) == [2, 5]
    found = [
        f"{path.relative_to(ROOT)}:{line}"
        for package in ALLOWED
        for path in sorted((ROOT / package).rglob("*.py"))
        if path.relative_to(ROOT).parts[:2] != ("teleop", "cli")
        for line in signal_handler_calls(path)
    ]
    assert not found, "only teleop/cli/ installs signal handlers (teleop/cli/signals.py):\n" + "\n".join(found)


DOOR = Path("teleop") / "web" / "viser_internals"  # the one folder that may use viser's, mjviser's, websockets' internals
LIBRARIES = ("viser", "mjviser", "websockets")


def behind_the_door(relative: Path) -> bool:
    """Whether a file (relative to the checkout) is in teleop/web/viser_internals/."""
    return relative.parts[:len(DOOR.parts)] == DOOR.parts


def viser_internals_touched(path: Path) -> list[str]:
    """Where a file relies on viser's or websockets' internals: a private viser module or name
    (`viser._messages`, `from viser import _x`, `viser._x` as an attribute), a client's
    `_websock_connection`, or websockets' modules as objects to patch (`import websockets...`,
    assigning or setattr on them, `patch("websockets....")`)."""
    found: list[str] = []

    def rooted_at(node: ast.AST, root: str) -> bool:
        while isinstance(node, ast.Attribute):
            node = node.value
        return isinstance(node, ast.Name) and node.id == root

    def private(dotted: str) -> bool:
        return any(part.startswith("_") for part in dotted.split(".")[1:])

    for node in ast.walk(parsed(path)):
        line = getattr(node, "lineno", 0)
        if isinstance(node, ast.Import):
            for alias in node.names:
                top = alias.name.split(".")[0]
                if (top == "viser" and private(alias.name)) or top == "websockets":
                    found.append(f"{line}: import {alias.name}")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "viser":
            if private(node.module) or any(a.name.startswith("_") for a in node.names):
                found.append(f"{line}: from {node.module} import {', '.join(a.name for a in node.names)}")
        elif isinstance(node, ast.Attribute):
            if node.attr.startswith("_websock") or (node.attr.startswith("_") and rooted_at(node.value, "viser")):
                found.append(f"{line}: .{node.attr}")
        elif isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Attribute) and rooted_at(t, "websockets") for t in targets):
                found.append(f"{line}: assigns to websockets")
        elif isinstance(node, ast.Call) and node.args:
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            first = node.args[0]
            if name == "setattr" and rooted_at(first, "websockets"):
                found.append(f"{line}: setattr on websockets")
            elif name in ("patch", "setattr") and isinstance(first, ast.Constant) and isinstance(first.value, str) \
                    and (first.value.startswith("websockets.") or first.value.startswith("viser._")):
                found.append(f"{line}: patches {first.value}")
    return sorted(found, key=lambda entry: int(entry.split(":")[0]))


def test_the_viser_internals_check_can_fail(tmp_path):
    sample = tmp_path / "sample.py"
    sample.write_text(
        "import viser\nimport websockets.asyncio.server\nfrom viser._messages import RunJavascriptMessage\n"
        "from viser import _messages\nfrom websockets.asyncio.server import ServerConnection\n\n"
        "def f(client, monkeypatch):\n    client._websock_connection.queue_message(None)\n"
        "    websockets.asyncio.server.serve = None\n    x = viser._messages\n"
        "    monkeypatch.setattr('websockets.asyncio.server.serve', None)\n    client.client_id\n")
    assert [entry.split(":")[0] for entry in viser_internals_touched(sample)] == \
        ["2", "3", "4", "8", "9", "10", "11"]


def test_only_the_door_touches_viser_or_websockets_internals():
    """Issue 19, 48: viser's and websockets' internals are used in teleop/web/viser_internals/ only
    (tests/test_viser_contract.py checks them against the installed releases)."""
    found = [
        f"{path.relative_to(ROOT)}:{entry}"
        for package in [*ALLOWED, "bench"]
        for path in sorted((ROOT / package).rglob("*.py"))
        if not behind_the_door(path.relative_to(ROOT))
        for entry in viser_internals_touched(path)
    ]
    assert not found, f"only {DOOR}/ may use viser's or websockets' internals:\n" + "\n".join(found)
    assert any(viser_internals_touched(path) for path in (ROOT / DOOR).rglob("*.py"))  # the check sees them where they are


def is_private(name: str) -> bool:
    """`_x` or `__x`, not a dunder (`__x__`) and not `_` alone."""
    return len(name) > 1 and name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


@lru_cache(maxsize=None)
def library_private_names() -> frozenset[str]:
    """Every private name the installed viser, mjviser and websockets define or use: attributes (`x._impl`), functions,
    methods and classes (`def _queue_update`), and names assigned (`self._mesh_groups = ...`), read from their
    sources with `ast`."""
    names: set[str] = set()
    for library in LIBRARIES:
        spec = importlib.util.find_spec(library)
        assert spec is not None and spec.submodule_search_locations, f"{library} is not installed"
        for folder in spec.submodule_search_locations:
            for path in sorted(Path(folder).rglob("*.py")):
                for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
                    if isinstance(node, ast.Attribute):
                        names.add(node.attr)
                    elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                        names.add(node.name)
                    elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                        names.add(node.id)
    return frozenset(name for name in names if is_private(name))


def private_accesses(path: Path) -> list[str]:
    """Private attributes a file reads or writes on objects that may be viser's, mjviser's or websockets':
    `x._name` (or getattr/setattr/hasattr/delattr(x, "_name")) whose receiver is not `self`, `cls` or a module the
    file imports with `import` (the stdlib's, ours), when the file imports from those libraries or the name is one
    of their private names (library_private_names)."""
    tree = parsed(path)
    uses_library = False
    modules: set[str] = set()  # names bound by `import x` / `import x as y` to modules not of those libraries
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                top = alias.name.split(".")[0]
                if top in LIBRARIES:
                    uses_library = True
                else:
                    modules.add(alias.asname or top)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and node.module.split(".")[0] in LIBRARIES:
            uses_library = True
    known = library_private_names()
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            name, receiver = node.attr, node.value
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
              and node.func.id in ("getattr", "setattr", "hasattr", "delattr") and len(node.args) >= 2
              and isinstance(node.args[1], ast.Constant) and isinstance(node.args[1].value, str)):
            name, receiver = node.args[1].value, node.args[0]
        else:
            continue
        if not is_private(name) or (isinstance(receiver, ast.Name) and (receiver.id in ("self", "cls") or receiver.id in modules)):
            continue
        if uses_library or name in known:
            found.append(f"{node.lineno}: {ast.unparse(receiver)}.{name}")
    return sorted(found, key=lambda entry: int(entry.split(":")[0]))


def private_uses_outside_the_door(root: Path) -> list[str]:
    """private_accesses in every module of a checkout at `root` (the library, teleop/, bench/) but the door's."""
    return [
        f"{path.relative_to(root)}:{entry}"
        for package in [*ALLOWED, "bench"]
        for path in sorted((root / package).rglob("*.py"))
        if not behind_the_door(path.relative_to(root))
        for entry in private_accesses(path)
    ]


def test_the_private_access_check_can_fail(tmp_path):
    """A planted `handle._impl` outside the door is found, the same file behind it is not; in a file that imports
    viser any `x._name` counts, in one that does not only viser's, mjviser's and websockets' own names do."""
    assert {"_impl", "_websock_connection", "_mesh_groups", "_queue_update", "_any_decor_visible"} <= library_private_names()
    planted = "def poses(handle):\n    return handle._impl.props\n"
    outside = tmp_path / "teleop" / "web" / "session_page" / "planted.py"
    inside = tmp_path / DOOR / "planted.py"
    for path in (outside, inside):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(planted)
    assert private_uses_outside_the_door(tmp_path) == ["teleop/web/session_page/planted.py:2: handle._impl"]
    sample = tmp_path / "bench" / "sample.py"
    sample.parent.mkdir()
    sample.write_text(
        "import os\nimport argparse\nfrom viser import ViserServer\n\n"
        "class A:\n    def f(self, server, scene):\n        self._mine = os._exit\n"
        "        server._brand_new_private\n        getattr(scene, '_mesh_groups')\n"
        "        return argparse._SubParsersAction, self.__class__\n")
    assert [entry.split(": ")[1] for entry in private_accesses(sample)] == ["server._brand_new_private", "scene._mesh_groups"]
    sample.write_text("def f(device, handle):\n    device._listener.join()\n    return handle._websock_connection\n")
    assert [entry.split(": ")[1] for entry in private_accesses(sample)] == ["handle._websock_connection"]


def test_no_private_attribute_of_viser_mjviser_or_websockets_is_used_outside_the_door():
    """Issue 48: any `x._name` on an object that may be viser's, mjviser's or websockets' lives in
    teleop/web/viser_internals/ (its package docstring says why each exists and what upstream change would retire it)."""
    found = private_uses_outside_the_door(ROOT)
    assert not found, f"private names of {', '.join(LIBRARIES)} are used only in {DOOR}/:\n" + "\n".join(found)
    assert private_accesses(ROOT / DOOR / "scene_stream.py")  # the check sees them where they are


# -- inside teleop/web/: a room per page, what two pages use in shared/ (issue 56, item 7) -------------------------
# A page's room (session_page/, replay_page/, review_page/, any new one) imports no other page's room, so what two
# pages use cannot stay in one of them: it lives in shared/. shared/ imports no page (the door, yes: its pages draw
# through viser); the door imports no page, and of shared/ only the gate (guarded_start puts it in front of viser).
# The campaign's lobby is a page too: teleop/campaign/ takes only shared/ of the web. The commands (cli/) and
# `import teleop` start pages, so they import them.
COMMON_ROOMS = ("shared", "viser_internals")
DOOR_MAY_TAKE = ("teleop.web.shared.access",)  # the gate's rules, for guarded_start.start_guarded


def web_room(module: str) -> str | None:
    """teleop.web.session_page.app -> session_page; teleop.web (the package itself) and modules outside it -> None."""
    parts = module.split(".")
    return parts[2] if parts[:2] == ["teleop", "web"] and len(parts) > 2 else None


def web_room_violations(root: Path) -> list[str]:
    """Every import (inside functions too) that crosses the web folder's rooms against the rule above."""
    graph = module_graph(root, ["teleop"], module_level_only=False)
    bad = []
    for module, targets in graph.items():
        room = web_room(module)
        for target, where in targets.items():
            to = web_room(target)
            if to is None or to == room:
                continue
            if room is None:
                allowed = module.split(".")[:2] != ["teleop", "campaign"] or to == "shared"
            elif room == "shared":
                allowed = to == "viser_internals"
            elif room == "viser_internals":
                allowed = target in DOOR_MAY_TAKE
            else:
                allowed = to in COMMON_ROOMS
            if not allowed:
                bad.append(f"{where}: {module} imports {target}")
    return bad


def test_the_web_room_check_can_fail(tmp_path):
    files = {
        "teleop/web/a_page/x.py": "from teleop.web.shared import s\nfrom teleop.web.b_page.y import Y\n",
        "teleop/web/b_page/y.py": "def f():\n    from teleop.web.a_page import x\n",
        "teleop/web/shared/s.py": "from teleop.web.viser_internals.d import D\nfrom teleop.web.a_page.x import X\n",
        "teleop/web/viser_internals/d.py": "from teleop.web.shared.access import Gate\nfrom teleop.web.shared.s import S\n",
        "teleop/web/shared/access.py": "",
        "teleop/campaign/lobby.py": "from teleop.web.shared.s import S\nfrom teleop.web.a_page.x import X\n",
        "teleop/cli/serve.py": "from teleop.web.a_page.x import X\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert sorted(web_room_violations(tmp_path)) == [
        "teleop/campaign/lobby.py:2: teleop.campaign.lobby imports teleop.web.a_page.x",
        "teleop/web/a_page/x.py:2: teleop.web.a_page.x imports teleop.web.b_page.y",
        "teleop/web/b_page/y.py:2: teleop.web.b_page.y imports teleop.web.a_page.x",
        "teleop/web/shared/s.py:2: teleop.web.shared.s imports teleop.web.a_page.x",
        "teleop/web/viser_internals/d.py:2: teleop.web.viser_internals.d imports teleop.web.shared.s",
    ]


def test_what_two_pages_use_lives_in_shared():
    """Issue 56, item 7: no page's room imports another's (the replay viewer once took the session page's drawing,
    input channel, keyboard script and view quality), the lobby takes only shared/, shared/ takes no page."""
    rooms = {p.name for p in (ROOT / "teleop" / "web").iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert {"session_page", "replay_page", "review_page", *COMMON_ROOMS} <= rooms
    bad = web_room_violations(ROOT)
    assert not bad, "a page's room imports only itself, shared/ and viser_internals/ (move what two pages use " \
                    "into teleop/web/shared/):\n" + "\n".join(bad)


# The gate is plain Python: the stdlib servers (the review page, the campaign lobby) ask it without loading viser
# or its wire format (msgspec). Checked in a fresh interpreter: what an import really loads, not what the source
# seems to say. (Those servers read episodes, whose MCAP chunks bring zstandard; the gate itself loads neither
# that nor websockets.)
VISER_AND_ITS_WIRE = ("viser", "mjviser", "msgspec")


def modules_loaded_by(module: str, names: tuple[str, ...]) -> list[str]:
    """Which of `names` (top-level packages) a fresh interpreter has loaded after `import module`."""
    import json
    import subprocess
    import sys

    probe = (f"import json, sys\nimport {module}\n"
             f"print(json.dumps(sorted(n for n in {list(names)!r} if n in sys.modules)))\n")
    done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_the_loaded_modules_probe_sees_an_import():
    assert modules_loaded_by("teleop.web.viser_internals.guarded_start", VISER_AND_ITS_WIRE) == ["msgspec", "viser"]


@pytest.mark.parametrize("module, unwanted", [
    ("teleop.web.shared.access", (*VISER_AND_ITS_WIRE, "zstandard", "websockets")),
    ("teleop.web.shared.stdlib_http", (*VISER_AND_ITS_WIRE, "zstandard", "websockets")),
    ("teleop.web.review_page.server", VISER_AND_ITS_WIRE),
    ("teleop.campaign.lobby", VISER_AND_ITS_WIRE),
])
def test_the_gate_and_the_stdlib_servers_load_no_viser(module, unwanted):
    """Issue 56, item 7: the gate's rules are apart from viser's start (teleop.web.viser_internals.guarded_start)."""
    loaded = modules_loaded_by(module, unwanted)
    assert loaded == [], f"importing {module} loads {loaded}: the gate and the stdlib servers need none of them"
