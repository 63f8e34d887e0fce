"""Every task can really be done: its example script succeeds on two seeds, seed 0 in a fresh process as a user
runs it, seed 1 through the CLI's entry point in this process (the same command, without ~2 s of imports)."""

from __future__ import annotations

import json

import pytest

from tests.support import ROOT, run_json, run_main

CASES = [
    ("stack", "panda", "stack_pick.json"),
    ("pick_place", "panda", "pick_place.json"),
    ("door", "panda", "door_push.json"),
    ("handover", "bimanual", "handover.json"),
    ("lift", "ur5e", "lift_pick.json"),
]


@pytest.mark.parametrize("scene,robot,script", CASES)
@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.e2e)])  # a whole episode each
def test_example_script_succeeds(scene, robot, script, seed):
    argv = ["run", "--device", f"script:{ROOT / 'scenes' / 'scripts' / script}", "--scene", scene, "--robot", robot,
            "--seed", str(seed), "--json"]
    if seed == 0:
        out = run_json(*argv)
    else:
        result = run_main(*argv)
        assert result.returncode == 0, result.stderr[-2000:]
        out = json.loads(result.stdout)
    assert out["success"] is True, out
    assert out["ik_failures"] == 0
