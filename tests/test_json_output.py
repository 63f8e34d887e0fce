"""Every `--json` command prints one JSON value on stdout and nothing else (issue 10, item 1).

Each command runs in a fresh process as a user would run it (`teleop ... --json > out.json`);
the whole of stdout must parse. To cover a new `--json` command, add a row to COMMANDS
and a bad input to BAD_INPUTS (a command that fails answers `{"error": ...}`, exit 2).
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from tests.support import ROOT, assert_one_line_error, run_cli, write_script

# (id, argv with {script}, {mcap}, {hdf5}, {out} filled in, the JSON type printed)
COMMANDS = [
    ("run", ["run", "--device", "script:{script}", "--json"], dict),
    ("run-record", ["run", "--device", "script:{script}", "--record", "{out}/rec", "--json"], dict),
    ("inspect", ["inspect", "{mcap}", "--json"], dict),
    ("replay-verify", ["replay", "{hdf5}", "--verify", "--json"], dict),
    ("convert", ["convert", "{mcap}", "--to", "hdf5", "{out}/converted.hdf5", "--json"], dict),
    ("devices", ["devices", "--json"], dict),
    ("video", ["video", "{mcap}", "--out", "{out}/v.gif", "--size", "32x24", "--json"], dict),
    ("bench-control", ["bench", "--only", "control", "--quick", "--json"], dict),
    ("perceive", ["perceive", "--scene", "lift", "--image", "{out}/seen.png", "--json"], dict),
]  # viser's banner (printed to stdout by `bench --only web`, ~50 s) is checked in one process below


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


def test_json_command_usage_error_prints_one_error_object():
    """Issue 38 item 5: a bad input still answers on stdout, with the line stderr gives (was: nothing)."""
    result = run_cli("bench", "--only", "contrl", "--json")
    assert_one_line_error(result, "--only contrl", "unknown bench")
    value = json.loads(result.stdout)
    assert set(value) == {"error"} and "--only contrl: unknown bench" in value["error"]
    assert result.stderr.strip().endswith(value["error"])


# A bad input for every command that takes --json ({tmp}: an empty folder): issue 38 item 5.
BAD_INPUTS: dict[str, tuple[list[str], str]] = {
    "scenes": (["scenes", "{tmp}/nope.toml", "--json"], "nope.toml"),
    "run": (["run", "--device", "script:{tmp}/nope.json", "--json"], "nope.json"),
    "bench": (["bench", "--only", "contrl", "--json"], "contrl"),
    "inspect": (["inspect", "{tmp}/nope.mcap", "--json"], "nope.mcap"),
    "convert": (["convert", "{tmp}/nope.mcap", "--to", "hdf5", "{tmp}/out.hdf5", "--json"], "nope.mcap"),
    "replay": (["replay", "{tmp}/nope.hdf5", "--verify", "--json"], "nope.hdf5"),
    "devices": (["devices", "--json", "--no-such-flag"], "--no-such-flag"),
    "annotate": (["annotate", "{tmp}", "--json"], "no episode files"),
    "generate": (["generate", "{tmp}", "--out", "{tmp}/gen", "--num", "1", "--json"], "no source episodes"),
    "eval": (["eval", "--policy", "{tmp}/nope", "--episodes", "1", "--json"], "nope"),
    "video": (["video", "{tmp}", "--out", "{tmp}/v.mp4", "--json"], "no episode files"),
    "perceive": (["perceive", "--scene", "no_such_task", "--image", "{tmp}/seen.png", "--json"], "no_such_task"),
}
# More ways in for `run`: a bad task, a usage error (argparse's own), a script naming what the scene lacks.
RUN_BAD = {
    "task": (["run", "--scene", "no_such_task", "--device", "script:{script}", "--json"], "no_such_task"),
    "usage": (["run", "--json"], "--device"),
    "script-body": (["run", "--device", "script:{badbody}", "--json"], "no_such_body"),
}


def json_commands() -> set[str]:
    """The subcommands whose parser takes --json, read from the CLI's own parser."""
    import argparse

    from teleop.cli.entry import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {name for name, p in sub.choices.items() if any("--json" in a.option_strings for a in p._actions)}


def test_every_json_command_has_a_bad_input_to_answer():
    assert json_commands() == set(BAD_INPUTS)


def _error_object(result: subprocess.CompletedProcess, needle: str) -> dict:
    assert result.returncode == 2, f"exit {result.returncode}: {result.stderr[-2000:]}"
    assert "Traceback" not in result.stderr
    try:
        value = json.loads(result.stdout)  # the whole of stdout: exactly one object
    except json.JSONDecodeError as exc:
        pytest.fail(f"stdout is not one JSON value ({exc}):\n{result.stdout[:2000]!r}")
    assert isinstance(value, dict) and isinstance(value.get("error"), str) and needle in value["error"], value
    assert "\n" not in value["error"]
    return value


@pytest.mark.parametrize("command", sorted(BAD_INPUTS))
def test_json_command_answers_a_bad_input_with_one_error_object(command, tmp_path):
    argv, needle = BAD_INPUTS[command]
    _error_object(run_cli(*[a.format(tmp=tmp_path) for a in argv]), needle)


@pytest.mark.parametrize("case", sorted(RUN_BAD))
def test_run_json_answers_a_bad_task_usage_or_script(case, files, tmp_path):
    badbody = write_script(tmp_path / "badbody.json", [{"duration": 0.1, "move": [0, 0, 0.01]},
                                                       {"duration": 0.1, "to_body": "no_such_body"}])
    argv, needle = RUN_BAD[case]
    result = run_cli(*[a.format(script=files["script"], badbody=badbody, out=tmp_path) for a in argv])
    value = _error_object(result, needle)
    if case != "usage":  # a TeleopError: stdout and stderr say the same one line
        assert_one_line_error(result, value["error"])


def test_json_command_answers_an_error_a_bug_and_silence_once():
    """The entry point's one place (json_command): an error, a bug or no result each give one object;
    a command that printed its object before failing is not answered twice."""
    code = textwrap.dedent(
        """
        import json, sys
        from scenes.errors import TeleopError
        from teleop.cli.json_output import json_command, print_json
        case = sys.argv[1]
        try:
            with json_command("x"):
                if case == "error":
                    raise TeleopError("bad file\\nsecond line")
                if case == "bug":
                    raise ZeroDivisionError("division by zero")
                if case == "printed":
                    print_json({"partial": 1})
                    raise TeleopError("disk full")
        except Exception:
            pass
        """
    )
    expected = {
        "error": {"error": "bad file"},
        "bug": {"error": "internal error: ZeroDivisionError: division by zero"},
        "silent": {"error": "teleop x ended without a result"},
        "printed": {"partial": 1},
    }
    for case, value in expected.items():
        result = subprocess.run([sys.executable, "-c", code, case], capture_output=True, text=True, cwd=ROOT, timeout=60)
        assert result.returncode == 0, result.stderr
        assert result.stdout.count("\n") == 1 and json.loads(result.stdout) == value, (case, result.stdout)


def test_json_mode_sends_python_c_and_child_writes_to_stderr():
    """Writes through sys.stdout, a stdout captured before, fd 1, a child process and viser's banner (what
    `teleop bench --only web --json` starts) all land on stderr."""
    code = textwrap.dedent(
        """
        import os, subprocess, sys
        import viser
        from rich.console import Console
        from teleop.cli.json_output import json_stdout, print_json
        early = sys.stdout
        with json_stdout():
            print("python print")
            early.write("old sys.stdout\\n")
            Console().print("rich console")
            os.write(1, b"fd 1\\n")
            subprocess.run([sys.executable, "-c", "print('child process')"], check=True)
            server = viser.ViserServer(host="127.0.0.1", port=0)  # verbose: its banner, on stdout without json_stdout
            print("viser on port", server.get_port())
            server.stop()
            print_json({"ok": True})
            print("after the JSON")
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout == '{"ok": true}\n'
    port = result.stderr.split("viser on port ", 1)[1].split()[0]
    assert f"http://127.0.0.1:{port}" in result.stderr  # the banner's address line
    for line in ("python print", "old sys.stdout", "rich console", "fd 1", "child process", "after the JSON"):
        assert line in result.stderr
