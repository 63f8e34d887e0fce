"""Issue 37, quick parts: a task file's per-arm subtasks and `[[constraint]]`s, checked when read (one line,
exit 2 from `teleop scenes FILE`), and a recorded two-arm episode annotated per arm (e2e: it records one)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import teleop
from replay.subtasks.sidecar import AnnotationError, Subtask, check_subtasks, read_subtasks
from scenes.tasks.file_task import load_task_file
from scenes.tasks.file_values import TaskFileError
from scenes.tasks.registry import find_task
from teleop.cli.entry import main
from tests.support import ROOT

TWO_ARMS = '''
name = "two_arm_checks"
instruction = "Put each cube down with its own arm."
robots = ["bimanual"]
success = "lifted(a, 0.05) and lifted(b, 0.05)"
subtasks = [
  {{arm = "left", object = "a", kind = "grasp"}},
  {{arm = "left", object = "world", kind = "place"}},
  {{arm = "{right}", object = "b", kind = "grasp"}},
  {{arm = "{right}", object = "world", kind = "place"}},
]
{constraints}

[[object]]
name = "a"
box = ["1 size", "1 size", "1 size"]
region = {{x = ["-1.5 spread", "-1.0 spread"], y = ["-0.5 spread", "0.5 spread"]}}

[[object]]
name = "b"
box = ["1 size", "1 size", "1 size"]
region = {{x = ["1.0 spread", "1.5 spread"], y = ["-0.5 spread", "0.5 spread"]}}
'''
SEQ = '[[constraint]]\nkind = "sequential"\nfirst = {first}\nthen = {then}\n'
COORD = '[[constraint]]\nkind = "coordinated"\nsubtasks = {refs}\n'

BAD = {
    "an arm that does not exist": (SEQ.format(first='["middle", 0]', then='["right", 0]'), "'middle' is not an arm"),
    "a subtask index out of range": (SEQ.format(first='["left", 1]', then='["right", 2]'), "subtask 2 is out of range"),
    "a cycle of sequential constraints": (SEQ.format(first='["left", 1]', then='["right", 0]')
                                          + SEQ.format(first='["right", 1]', then='["left", 0]'), "cycle"),
    "a coordinated pair against a sequential one": (COORD.format(refs='[["left", 0], ["right", 0]]')
                                                    + SEQ.format(first='["left", 0]', then='["right", 0]'), "cycle"),
    "a subtask on an arm the robot lacks": ("", "'centre' is not an arm of this task"),
}


def write(tmp_path: Path, constraints: str, right: str = "right") -> Path:
    path = tmp_path / "two_arm_checks.toml"
    path.write_text(TWO_ARMS.format(constraints=constraints, right=right))
    return path


def test_a_two_arm_task_file_reads_its_arms_and_constraints(tmp_path):
    task = load_task_file(write(tmp_path, SEQ.format(first='["left", 0]', then='["right", 0]')
                                + COORD.format(refs='[["left", 1], ["right", 1]]')))
    assert [(s.arm, s.object) for s in task.subtasks] == [("left", "a"), ("left", "world"), ("right", "b"), ("right", "world")]
    assert [c.to_json() for c in task.constraints] == [
        {"kind": "sequential", "first": ["left", 0], "then": ["right", 0]},
        {"kind": "coordinated", "subtasks": [["left", 1], ["right", 1]]}]
    handover = find_task("handover")
    assert {s.arm for s in handover.subtasks} == {"left", "right"}
    assert {c.kind for c in handover.constraints} == {"sequential", "coordinated"}
    assert all(not s.arm for s in find_task("pick_place").subtasks)  # a one-arm task: no arms, as before


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_constraints_are_one_line_and_exit_2(case, tmp_path, capsys):
    text, needle = BAD[case]
    path = write(tmp_path, text, right="centre" if "lacks" in case else "right")
    with pytest.raises(TaskFileError) as info:
        load_task_file(path)
    assert "\n" not in str(info.value) and needle in str(info.value) and str(path) in str(info.value)
    capsys.readouterr()
    assert main(["scenes", str(path)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and needle in err[0], err


def test_a_one_arm_task_takes_no_arm(tmp_path):
    path = tmp_path / "one.toml"
    path.write_text('name = "one"\ninstruction = "Lift it."\nrobots = ["panda"]\nsuccess = "lifted(a, 0.05)"\n'
                    'subtasks = [{object = "a", kind = "grasp", arm = "left"}]\n'
                    '[[object]]\nname = "a"\nbox = ["1 size", "1 size", "1 size"]\n')
    with pytest.raises(TaskFileError, match="one-arm task's subtasks take no arm"):
        load_task_file(path)


@pytest.mark.e2e  # 1.6 s: an episode recorded, then its contacts replayed
def test_a_recorded_two_arm_episode_is_annotated_per_arm(tmp_path, capsys):
    session = teleop.Session(scene="handover", robot="bimanual", seed=0, control_hz=30)
    with teleop.Recorder(session, tmp_path, verify="off") as rec:
        result = teleop.run_episode(session, [teleop.ScriptDevice(ROOT / "scenes" / "scripts" / "handover.json")])
    assert result.success
    (path,) = rec.paths
    capsys.readouterr()
    assert main(["annotate", str(path), "--auto", "--json"]) == 0
    (ep,) = json.loads(capsys.readouterr().out)["episodes"]
    subtasks = [Subtask(s["object"], s["start"], s["end"], s.get("arm", "")) for s in ep["subtasks"]]
    assert [(s.arm, s.object) for s in subtasks] == [("left", "cube"), ("left", "world"), ("right", "cube")]
    steps = teleop.load_episode(path).steps
    left, right = subtasks[:2], subtasks[2:]
    assert left[0].start == 0 and left[1].start == left[0].end and left[1].end == steps  # each arm covers the episode
    assert right[0].start == 0 and right[0].end == steps
    # the left grasp ends once its fingers closed on the cube: after the script's close (its 3rd step, from 2.0 s)
    assert round(2.0 * 30) <= left[0].end <= round(2.5 * 30) + 18, left
    assert read_subtasks(path, steps) == subtasks
    with pytest.raises(AnnotationError, match="right arm"):  # each arm's own subtasks must cover the episode
        check_subtasks([*left, Subtask("cube", 0, steps - 1, "right")], steps)


def test_hand_edits_of_a_two_arm_annotation_change_one_arm_at_a_time(tmp_path):
    from replay.subtasks.edit import EditRefused, SubtaskEdits

    steps = 300
    edits = SubtaskEdits([Subtask("cube", 0, 60, "left"), Subtask("world", 60, steps, "left"),
                          Subtask("cube", 0, steps, "right")], steps)
    assert edits.arm == "left" and edits.boundaries == [60]
    edits.select_arm("right")
    assert edits.boundaries == []
    edits.add(120, "world")
    edits.move(0, 150)
    assert [(s.arm, s.object, s.start, s.end) for s in edits.all_subtasks] == [
        ("left", "cube", 0, 60), ("left", "world", 60, steps), ("right", "cube", 0, 150), ("right", "world", 150, steps)]
    check_subtasks(edits.all_subtasks, steps)  # what the viewer saves
    with pytest.raises(EditRefused, match="no arm 'middle'"):
        edits.select_arm("middle")
    one = SubtaskEdits([Subtask("cube", 0, 40), Subtask("bin", 40, 90)], 90)  # one arm: as before
    one.move(0, 50)
    assert one.all_subtasks == one.subtasks == [Subtask("cube", 0, 50), Subtask("bin", 50, 90)]
