"""The warm process that forks `teleop` commands for the tests (tests/warm_cli.py) gives what a real
interpreter gives: the same exit code, stdout and stderr, the folder and environment asked for, a timeout
that ends the command; and it steps aside when the environment could change what the imports see."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest

from tests.support import PICK, ROOT, run_cli, wait_until
from tests.warm_cli import WARM

pytestmark = pytest.mark.e2e  # starts the warm process (LeRobot's imports: seconds of CPU)


def fresh(*args: str, cwd=ROOT, env: dict | None = None) -> subprocess.CompletedProcess:
    """`teleop ARGS` in a real interpreter, as run_cli would without the warm process."""
    env = {**os.environ, **(env or {}), "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "teleop", *args], capture_output=True, text=True, env=env, cwd=cwd,
                          timeout=300)


def test_a_forked_command_answers_as_a_real_interpreter_does(tmp_path):
    forked_before = WARM.forked
    for args in (("run", "--bogus"), ("robots", "--json"), ("inspect", str(tmp_path / "missing.mcap"), "--json")):
        warm, real = run_cli(*args), fresh(*args)
        assert (warm.returncode, warm.stdout, warm.stderr) == (real.returncode, real.stdout, real.stderr), args
    assert WARM.forked == forked_before + 3, "the commands were not forked from the warm process"
    assert WARM.cpu_s > 0


def test_a_forked_command_works_in_the_folder_and_environment_asked_for(tmp_path):
    before = WARM.forked
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    summary = json.loads(run_cli("run", "--device", f"script:{PICK}", "--record", "rel", "--json", cwd=tmp_path,
                                 env={"TMPDIR": str(scratch)}).stdout)
    assert summary["success"] is True and (tmp_path / "rel" / "episode_000000.mcap").is_file()
    assert WARM.forked == before + 1
    # a variable an import could read: a real interpreter, which sees it
    result = run_cli("run", "--bogus", env={"HF_LEROBOT_HOME": str(tmp_path)})
    assert result.returncode == 2 and WARM.forked == before + 1
    assert not WARM.usable_for({**WARM.env, "PYTHONPATH": str(tmp_path)})
    assert WARM.usable_for({**WARM.env, "TMPDIR": str(scratch), "PYTEST_CURRENT_TEST": "x"})


def test_a_timeout_ends_the_forked_command(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(subprocess.TimeoutExpired):
        run_cli("serve", "--port", str(port), timeout=3)

    def port_free() -> bool:
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
            return True

    wait_until(port_free, 30, "the timed-out server to end and free its port")
