"""`teleop run`, `robots`, `scenes` end to end, and their one-line errors.

One run of each kind in a fresh process, as a user starts it; the rest through the CLI's entry point in
this process (`run_main`: the same parser, command and error line, without ~1-2 s of imports a run).
"""

from __future__ import annotations

import json

import pytest

from tests.support import ROOT, assert_one_line_error, run_cli, run_json, run_main

PICK = str(ROOT / "scenes" / "scripts" / "lift_pick.json")


def main_json(*args: str) -> dict:
    """`teleop ARGS... --json` in this process: exit 0 and the one JSON object it printed."""
    result = run_main(*args)
    assert result.returncode == 0, f"exit {result.returncode}: {result.stderr[-2000:]}"
    return json.loads(result.stdout)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_scripted_pick_lifts_the_cube(seed):
    run = run_json if seed == 0 else main_json  # seed 0 in a fresh process
    out = run("run", "--device", f"script:{PICK}", "--scene", "lift", "--robot", "panda", "--seed", str(seed), "--json")
    assert out["success"] is True
    assert out["ik_failures"] == 0
    assert out["steps"] == 144 and out["sim_seconds"] == pytest.approx(4.8, abs=1e-4)
    for key in ("steps", "sim_seconds", "wall_seconds", "success", "ik_failures", "ee_tracking_error_mm"):
        assert key in out
    assert set(out["ee_tracking_error_mm"]) >= {"median", "max"}
    assert out["ee_tracking_error_mm"]["max"] < 10


def test_without_grasp_the_task_fails(tmp_script):
    """The success predicate is real: the same approach without closing the gripper fails."""
    script = tmp_script([
        {"duration": 1.5, "to_body": "cube", "offset": [0, 0, 0.12]},
        {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.0]},
        {"duration": 1.2, "move": [0, 0, 0.15]},
    ])
    out = main_json("run", "--device", f"script:{script}", "--json")
    assert out["success"] is False


def test_seconds_limits_the_run(tmp_script):
    script = tmp_script([{"duration": 5.0, "move": [0.05, 0, 0]}])
    out = main_json("run", "--device", f"script:{script}", "--seconds", "1", "--control-hz", "50", "--json")
    assert out["steps"] == 50
    assert out["sim_seconds"] == pytest.approx(1.0, abs=1e-9)


def test_robots_and_scenes_list_the_builtins():
    robots = run_cli("robots")
    assert robots.returncode == 0
    names = [line.split()[0] for line in robots.stdout.splitlines()]
    assert "panda" in names
    scenes = run_main("scenes")
    listed = [line.split()[0] for line in scenes.stdout.splitlines()]
    assert listed[:5] == ["lift", "stack", "pick_place", "door", "handover"]  # the built-ins first, then the library
    assert len(listed) >= 30 and len(set(listed)) == len(listed)


@pytest.mark.parametrize(
    "steps,needles",
    [
        ([{"duration": 1, "move": [0, 0]}], ["step 1", "'move'"]),
        ([{"duration": 1}, {"duration": -2}], ["step 2", "'duration'"]),
        ([{"duration": 1}, {"duration": 1, "gripper": "half"}], ["step 2", "'gripper'"]),
        ([{"duration": 1, "fly": [1, 2, 3]}], ["step 1", "'fly'"]),
        ([{"duration": 1, "to": [0, 0, 1], "move": [0, 0, 1]}], ["step 1", "'move'"]),
        ([{"duration": 1, "offset": [0, 0, 1]}], ["step 1", "'offset'"]),
        ([], ["empty"]),
    ],
)
def test_bad_scripts_give_one_line(tmp_script, steps, needles):
    script = tmp_script(steps)
    assert_one_line_error(run_main("run", "--device", f"script:{script}"), *needles)


def test_script_errors_at_runtime_name_the_step(tmp_script):
    script = tmp_script([{"duration": 0.2}, {"duration": 0.5, "to_body": "unicorn"}])
    assert_one_line_error(run_cli("run", "--device", f"script:{script}"), "step 2", "unicorn")  # a fresh process


def test_malformed_json_and_missing_script(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{steps: [")
    assert_one_line_error(run_main("run", "--device", f"script:{bad}"), "not valid JSON")
    assert_one_line_error(run_main("run", "--device", f"script:{tmp_path / 'nope.json'}"), "no such script")


def test_unknown_scene_robot_and_combination(tmp_script):
    script = tmp_script([{"duration": 0.1}])
    assert_one_line_error(run_main("run", "--device", f"script:{script}", "--scene", "juggle"), "unknown scene")
    assert_one_line_error(run_main("run", "--device", f"script:{script}", "--robot", "r2d2"), "unknown robot")
    assert_one_line_error(run_main("run", "--device", f"script:{script}", "--scene", "handover"), "handover")
    assert_one_line_error(run_main("run", "--device", f"script:{script}", "--control-hz", "0"), "control rate")
