"""run.sh installs only when the venv lacks what is asked for, and keeps pip's output in a log shown on failure.

Each test points TELEOP_VENV at a venv folder of its own: bin/teleop runs the real `teleop`, and bin/python
stands in for pip, failing the way an offline pip fails and leaving a trace that it was called, so a wrong
decision shows and the shared .venv is never installed into.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import ROOT

ALL_EXTRAS = "test,lerobot,train,cluster"  # what `./run.sh test` installs


def pyproject_hash() -> str:
    """The stamp's key: run.sh's `sha1sum <pyproject.toml | cut -c1-12`."""
    return hashlib.sha1((ROOT / "pyproject.toml").read_bytes()).hexdigest()[:12]


def make_venv(folder: Path, stamps: list[str]) -> Path:
    """A venv folder with the given install stamps (extras lists), the real teleop and a pip that fails."""
    bin_dir = folder / "bin"
    bin_dir.mkdir(parents=True)
    python = bin_dir / "python"
    python.write_text(f'#!/bin/sh\necho "$@" >> "{folder}/pip_calls"\necho "fake pip: no network"\necho "ERROR: boom" >&2\nexit 1\n')
    teleop = bin_dir / "teleop"
    teleop.write_text(f'#!/bin/sh\nPYTHONPATH="{ROOT}" exec "{sys.executable}" -m teleop "$@"\n')
    for path in (python, teleop):
        path.chmod(0o755)
    for extras in stamps:
        (folder / f".installed-{extras}").touch()
    return folder


def run_sh(venv: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "TELEOP_VENV": str(venv)}
    return subprocess.run([str(ROOT / "run.sh"), *args], capture_output=True, text=True, env=env, timeout=60, cwd=ROOT)


@pytest.mark.e2e  # starts the real `teleop` four times: seconds each
@pytest.mark.parametrize("stamps", [[ALL_EXTRAS], [""], ["lerobot", ""], ["lerobot,train", "test"]])
def test_a_venv_that_holds_the_extras_asked_for_is_not_installed_into(tmp_path, stamps):
    venv = make_venv(tmp_path / "venv", [f"{pyproject_hash()}-{extras}" for extras in stamps])
    result = run_sh(venv, "robots")
    assert result.returncode == 0, result.stderr
    assert "panda" in result.stdout
    assert "installing" not in result.stderr and "*****" not in result.stderr + result.stdout
    assert not (venv / "pip_calls").exists() and not (venv / "install.log").exists()


@pytest.mark.parametrize("stamps", [[], [f"{'0' * 12}-{ALL_EXTRAS}"]], ids=["no stamp", "another pyproject"])
def test_an_install_keeps_pip_quiet_and_shows_its_log_only_when_it_fails(tmp_path, stamps):
    venv = make_venv(tmp_path / "venv", stamps)
    result = run_sh(venv, "robots")
    assert result.returncode == 1
    assert (venv / "pip_calls").read_text().splitlines() == ["-m pip install -e ."]
    assert result.stdout == ""  # pip's output went to the log, shown on stderr because it failed
    log = (venv / "install.log").read_text()
    assert "fake pip: no network" in log and "ERROR: boom" in log
    assert f"failed; the end of {venv}/install.log:" in result.stderr
    assert "fake pip: no network" in result.stderr and "ERROR: boom" in result.stderr
    assert not list(venv.glob(f".installed-{pyproject_hash()}-*"))  # a failed install leaves no stamp
