"""`ServeOptions`: the one object a served session's settings travel in, from `teleop serve`'s flags, a
campaign's spec or a script's keywords, to `serve()` and `WebApp`."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

import teleop
from teleop.cli.entry import build_parser
from teleop.cli.serve import serve_options_from
from teleop.errors import UsageError
from teleop.web.session_page.serve_options import ServeOptions, asks_for_keyboard
from teleop.web.shared.access import resolve_token
from tests import browser as headless
from tests.support import run_cli


def cli_options(*flags: str) -> ServeOptions:
    """What `teleop serve FLAGS` serves with, built as the command builds it (no TELEOP_TOKEN in play)."""
    args = build_parser().parse_args(["serve", *flags])
    return serve_options_from(args, resolve_token(args.host, args.token, args.no_token, environ={}))


@pytest.mark.unit
def test_defaults_are_the_commands_defaults():
    """A script that names nothing is served as `teleop serve` with no flags is."""
    cli, default = cli_options(), ServeOptions()
    differ = {f.name for f in dataclasses.fields(ServeOptions) if getattr(cli, f.name) != getattr(default, f.name)}
    # The command decides page_keyboard from its --device words (its devices are opened before serve());
    # the options leave it to serve(), which decides it by the same rule from serve()'s default devices.
    assert differ <= {"page_keyboard"}, differ
    args = build_parser().parse_args(["serve"])
    serve_devices = inspect.signature(serve_in_browser()).parameters["devices"].default
    assert args.device.split(",") == list(serve_devices)
    assert cli.page_keyboard == asks_for_keyboard(list(serve_devices))
    assert default.page_keyboard is None


@pytest.mark.unit
def test_every_flag_reaches_its_field(tmp_path):
    defaults = ServeOptions()
    status = tmp_path / "status.json"
    options = cli_options("--host", "0.0.0.0", "--port", "9123", "--pos-speed", "0.3", "--rot-speed", "1.5",
                          "--policy-device", "cuda", "--keep-scene", "--status-file", str(status),
                          "--token", "a-secret-token", "--device", "gizmo")
    assert (options.host, options.port, options.pos_speed, options.rot_speed) == ("0.0.0.0", 9123, 0.3, 1.5)
    assert (options.policy_device, options.keep_scene, options.status_file) == ("cuda", True, status)
    assert options.token == "a-secret-token" and not options.no_token
    assert options.page_keyboard is False  # --device names no keyboard
    assert (options.host, options.port, options.keep_scene) != (defaults.host, defaults.port, defaults.keep_scene)
    opened = cli_options("--host", "0.0.0.0", "--no-token")
    assert opened.no_token and opened.token is None


@pytest.mark.unit
@pytest.mark.parametrize("field, value, words", [
    ("port", 70000, "--port"),
    ("port", -1, "--port"),
    ("port", "8080", "--port"),
    ("pos_speed", 0.0, "--pos-speed"),
    ("pos_speed", float("nan"), "--pos-speed"),
    ("rot_speed", -0.8, "--rot-speed"),
    ("status_period_s", 0, "status_period_s"),
    ("host", "", "--host"),
])
def test_a_bad_value_is_one_usage_error(field, value, words):
    with pytest.raises(UsageError) as caught:
        ServeOptions(**{field: value})
    message = str(caught.value)
    assert words in message and "\n" not in message
    with pytest.raises(UsageError):  # replace() checks again
        dataclasses.replace(ServeOptions(), **{field: value})


@pytest.mark.unit
def test_token_and_no_token_contradict():
    with pytest.raises(UsageError, match="contradict"):
        ServeOptions(token="a-secret-token", no_token=True)


@pytest.mark.unit
def test_options_are_frozen_and_paths_are_paths(tmp_path):
    options = ServeOptions(status_file=str(tmp_path / "s.json"))
    assert options.status_file == tmp_path / "s.json"
    with pytest.raises(dataclasses.FrozenInstanceError):
        options.port = 1  # type: ignore[misc]


@pytest.mark.unit
def test_the_scripting_serve_checks_before_it_serves():
    """`teleop.serve`: fields and serve()'s own arguments as keywords; a wrong name or value fails before a port is bound."""
    session = teleop.Session(scene="lift", robot="panda", seed=0, control_hz=30)
    port = headless.free_port()
    with pytest.raises(TypeError, match="prot"):
        teleop.serve(session, prot=port, devices=["gizmo"])
    with pytest.raises(UsageError, match="--pos-speed"):
        teleop.serve(session, teleop.ServeOptions(port=port), pos_speed=-1.0)
    with pytest.raises(TypeError, match="ServeOptions"):
        teleop.serve(session, ["gizmo"])  # devices went second before the options object
    with pytest.raises(TypeError, match="ServeOptions"):
        serve_in_browser()(session, ["gizmo"])


@pytest.mark.e2e  # a fresh `teleop` process
def test_a_bad_speed_is_one_line_and_exit_2():
    result = run_cli("serve", "--port", str(headless.free_port()), "--rot-speed", "0", timeout=120)
    assert result.returncode == 2, result.stderr
    assert "--rot-speed" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def serve_in_browser():
    """serve() itself (its module loads viser: only the tests that need it import it)."""
    from teleop.web.session_page.serve import serve

    return serve
