"""Every `--json` command prints one JSON value on stdout and nothing else (issue 10, item 1).

Each command runs in a fresh process as a user would run it (`teleop ... --json > out.json`);
the whole of stdout must parse. To cover a new `--json` command, add a row to COMMANDS.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from tests.conftest import ROOT, assert_one_line_error, run_cli, write_script

# (id, argv with {script}, {mcap}, {hdf5}, {out} filled in, the JSON type printed)
COMMANDS = [
    ("run", ["run", "--device", "script:{script}", "--json"], dict),
    ("run-record", ["run", "--device", "script:{script}", "--record", "{out}/rec", "--json"], dict),
    ("inspect", ["inspect", "{mcap}", "--json"], dict),
    ("replay-verify", ["replay", "{hdf5}", "--verify", "--json"], dict),
    ("convert", ["convert", "{mcap}", "--to", "hdf5", "{out}/converted.hdf5", "--json"], dict),
    ("devices", ["devices", "--json"], dict),
    ("bench-control", ["bench", "--only", "control", "--quick", "--json"], dict),
    ("bench-web", ["bench", "--only", "web", "--quick", "--json"], dict),  # viser prints a banner to stdout
]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    """A tiny script and one recorded episode in both formats."""
    tmp = tmp_path_factory.mktemp("json_output")
    script = write_script(tmp / "script.json", [{"duration": 0.2, "move": [0.0, 0.0, 0.02]}])
    record = tmp / "episodes"
    result = run_cli("run", "--device", f"script:{script}", "--record", str(record), "--format", "both", "--json")
    assert result.returncode == 0, result.stderr[-2000:]
    (mcap,) = record.glob("*.mcap")
    (hdf5,) = record.glob("*.hdf5")
    return {"script": str(script), "mcap": str(mcap), "hdf5": str(hdf5)}


@pytest.mark.parametrize("argv,kind", [pytest.param(a, k, id=i) for i, a, k in COMMANDS])
def test_json_command_prints_only_json_on_stdout(argv, kind, files, tmp_path):
    args = [a.format(out=tmp_path, **files) for a in argv]
    result = run_cli(*args)
    assert result.returncode == 0, f"exit {result.returncode}: {result.stderr[-2000:]}"
    try:
        value = json.loads(result.stdout)  # the whole of stdout, not its last line
    except json.JSONDecodeError as exc:
        pytest.fail(f"stdout is not one JSON value ({exc}):\n{result.stdout[:2000]}")
    assert isinstance(value, kind) and value


def test_json_command_usage_error_prints_nothing_on_stdout():
    result = run_cli("bench", "--only", "contrl", "--json")
    assert_one_line_error(result, "--only contrl", "unknown bench")
    assert result.stdout == ""


def test_json_mode_sends_python_c_and_child_writes_to_stderr():
    """Writes through sys.stdout, a stdout captured before, fd 1 and a child process all land on stderr."""
    code = textwrap.dedent(
        """
        import os, subprocess, sys
        from rich.console import Console
        from teleop.cli.json_output import json_stdout, print_json
        early = sys.stdout
        with json_stdout():
            print("python print")
            early.write("old sys.stdout\\n")
            Console().print("rich console")
            os.write(1, b"fd 1\\n")
            subprocess.run([sys.executable, "-c", "print('child process')"], check=True)
            print_json({"ok": True})
            print("after the JSON")
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout == '{"ok": true}\n'
    for line in ("python print", "old sys.stdout", "rich console", "fd 1", "child process", "after the JSON"):
        assert line in result.stderr
