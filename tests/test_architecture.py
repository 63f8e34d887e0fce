"""The import graph is a DAG with the app on top, checked on the source with `ast`.

scenes/ imports none of our folders; devices/ and recorder/ at most scenes/;
replay/ at most recorder/ and scenes/; teleop/ may import all. An import inside
a function counts like any other: hiding one there does not get around the rule.
"""

from __future__ import annotations

import ast
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


def imported_modules(path: Path) -> list[tuple[int, str, bool]]:
    """(line, module, inside a function) for every absolute import in a file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: list[tuple[int, str, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            nested = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                found.extend((child.lineno, alias.name, in_function) for alias in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                found.append((child.lineno, child.module, in_function))
            visit(child, nested)

    visit(tree, False)
    return found


def edges() -> list[tuple[str, int, str, str, bool]]:
    out = []
    for package in ALLOWED:
        for path in sorted((ROOT / package).rglob("*.py")):
            for line, module, in_function in imported_modules(path):
                out.append((str(path.relative_to(ROOT)), line, package, module, in_function))
    return out


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
    from teleop.web.panel import PanelDevice

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
