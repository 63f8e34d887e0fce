"""A normal (non-editable) install has every file the code opens: the wheel is built and compared
with the repository.

Every file tracked by git under the installed packages (teleop/, devices/, recorder/,
replay/, scenes/) must be in the wheel: code, and the data it opens at run time (robot
MJCF, scripts, the page's JavaScript and HTML, meshes and their convex parts, task
files). A file kind left out of pyproject.toml's package-data fails here by name.
.ci/wheel_check.sh then installs that wheel into a fresh environment and uses it.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("teleop", "devices", "recorder", "replay", "scenes")
pytestmark = pytest.mark.e2e


def tracked_package_files() -> set[str]:
    out = subprocess.run(["git", "ls-files", *PACKAGES], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return {line for line in out.splitlines() if line and (ROOT / line).is_file()}


def test_the_wheel_holds_every_file_of_the_packages(tmp_path):
    # Built from a clean copy of the checkout: setuptools' build/ folder would keep files from earlier builds.
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout.splitlines()
    source = tmp_path / "src"
    for name in listed:
        if (ROOT / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, source / name)
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", str(source), "-w", str(tmp_path)],
        capture_output=True, text=True, timeout=600,
    )
    assert build.returncode == 0, build.stderr[-2000:]
    (wheel,) = tmp_path.glob("mujoco_teleop-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = sorted(tracked_package_files() - names)
    assert not missing, "not in the wheel (add them to [tool.setuptools.package-data]):\n" + "\n".join(missing)
    assert "teleop/web/session_page/phone.html" in names and "scenes/robots/panda.xml" in names  # the two that went missing once
    assert not any(n.startswith(("tests/", "bench/")) for n in names)  # they stay in the checkout


def _declared_distributions() -> set[str]:
    """Every distribution pyproject.toml names: the core dependencies and every extra's (normalised names)."""
    import re
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    specs = list(project["dependencies"]) + [d for extra in project["optional-dependencies"].values() for d in extra]
    return {re.split(r"[\s\[<>=!~;]", spec, maxsplit=1)[0].lower().replace("_", "-") for spec in specs}


@pytest.mark.unit
def test_every_third_party_module_the_code_imports_is_declared():
    """A module the product code imports by name (at any level) comes from a distribution pyproject.toml declares:
    a dependency that only arrives with another package (websockets with viser) breaks when that one changes."""
    import ast
    import importlib.metadata
    import sys

    ours = {"teleop", "devices", "recorder", "replay", "scenes"}
    providers = importlib.metadata.packages_distributions()
    declared = _declared_distributions()
    # distributions that come with a declared one, by design, imported where the code works with that one's data:
    # LeRobot's dataset parts (its parquet and its video decoder), pynput's X11 client, mujoco's GL binding
    through = {"lerobot": {"torch", "pyarrow", "pandas", "torchcodec", "feetech-servo-sdk", "dynamixel-sdk", "pyserial"},
               "pynput": {"python-xlib"}, "mujoco": {"pyopengl"}}
    allowed = declared | {d for extra in through.values() for d in extra}
    missing = {}
    for package in sorted(ours):
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.split(".")[0]
                    if top in ours or top in sys.stdlib_module_names or top == "__future__":
                        continue
                    dists = {d.lower().replace("_", "-") for d in providers.get(top, [])}
                    if dists and not dists & allowed:
                        missing.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    assert not missing, f"imported but not declared in pyproject.toml: {missing}"


@pytest.mark.unit
def test_the_declared_check_sees_websockets_msgspec_and_zstandard():
    declared = _declared_distributions()
    assert {"websockets", "msgspec", "zstandard", "viser"} <= declared
