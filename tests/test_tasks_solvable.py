"""Every task can really be done: its example script succeeds, in a fresh process, on two seeds."""

from __future__ import annotations

import pytest

from tests.support import ROOT, run_json

CASES = [
    ("stack", "panda", "stack_pick.json"),
    ("pick_place", "panda", "pick_place.json"),
    ("door", "panda", "door_push.json"),
    ("handover", "bimanual", "handover.json"),
    ("lift", "ur5e", "lift_pick.json"),
]


@pytest.mark.parametrize("scene,robot,script", CASES)
@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.e2e)])  # a whole episode in a fresh process each
def test_example_script_succeeds(scene, robot, script, seed):
    out = run_json(
        "run", "--device", f"script:{ROOT / 'scenes' / 'scripts' / script}",
        "--scene", scene, "--robot", robot, "--seed", str(seed), "--json",
    )
    assert out["success"] is True, out
    assert out["ik_failures"] == 0
