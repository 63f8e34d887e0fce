"""Issue 35: the campaign file's checks, the seed ledger, invites and which task an operator gets.

All in-process and quick: no session process starts here (tests/test_campaign.py starts them).
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from teleop.campaign.file import check_operator_name, load_campaign
from teleop.campaign.ledger import count_task, invited, issue_invites, load_invites, next_episode_index, next_seed, state_dir
from teleop.cli.entry import main
from teleop.errors import UsageError

GOOD = """
name = "week1"
out = "data"
max_sessions = 3
session_minutes = 20
[[task]]
scene = "lift"
episodes = 5
[[task]]
scene = "stack"
episodes = 2
robot = "panda"
control_hz = 20
format = "both"
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "c.toml"
    path.write_text(text)
    return path


def test_a_good_file_reads_with_its_defaults(tmp_path):
    campaign = load_campaign(write(tmp_path, GOOD))
    assert campaign.name == "week1" and campaign.out == (tmp_path / "data").resolve()
    assert [(t.name, t.episodes, t.control_hz, t.format) for t in campaign.tasks] == \
        [("lift", 5, 30.0, "mcap"), ("stack", 2, 20.0, "both")]
    assert campaign.max_sessions == 3 and campaign.session_minutes == 20.0 and campaign.open
    assert campaign.tasks[0].instruction == "Pick up the red cube and lift it."


def test_a_task_file_is_found_relative_to_the_campaign_file(tmp_path):
    library = Path(__file__).resolve().parent.parent / "scenes" / "builtin_tasks" / "lift.toml"
    (tmp_path / "tasks").mkdir()
    (tmp_path / "tasks" / "bowl.toml").write_text(library.read_text())
    campaign = load_campaign(write(tmp_path, 'name = "c"\nout = "o"\noperators = ["ana", "bo"]\n'
                                             '[[task]]\nscene = "tasks/bowl.toml"\nepisodes = 1\nname = "bowl"\n'))
    assert campaign.tasks[0].scene == str((tmp_path / "tasks" / "bowl.toml").resolve())
    assert campaign.operators == ("ana", "bo") and not campaign.open


BAD = [
    ("name = 'c'\nout = 'o'\n", "at least one [[task]]"),
    ("out = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "name = None"),
    ("name = 'a b'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "name = 'a b'"),
    ("name = 'c'\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "out is required"),
    ("name = 'c'\nout = 'o'\nspeed = 2\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "unknown key 'speed'"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'nowhere'\nepisodes = 1\n", "task 1: unknown scene 'nowhere'"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'x.toml'\nepisodes = 1\n", "no such task file"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\n", "episodes is required"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 0\n", "episodes = 0"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 2.5\n", "episodes = 2.5"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 1\nformat = 'avi'\n", "format = 'avi'"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 1\nvary = 'wind'\n", "task 1: vary"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 1\ncontrol_hz = 0\n", "control_hz = 0"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 1\ncolour = 1\n", "task 1: unknown key 'colour'"),
    ("name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = 1\n[[task]]\nscene = 'lift'\nepisodes = 1\n",
     "two tasks are named 'lift'"),
    ("name = 'c'\nout = 'o'\nmax_sessions = 0\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "max_sessions = 0"),
    ("name = 'c'\nout = 'o'\nsession_minutes = -1\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "session_minutes = -1"),
    ("name = 'c'\nout = 'o'\noperators = 'all'\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "operators = 'all'"),
    ("name = 'c'\nout = 'o'\noperators = ['<b>x</b>']\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "no markup"),
    ("name = 'c'\nout = 'o'\noperators = ['ana', 'ana']\n[[task]]\nscene = 'lift'\nepisodes = 1\n", "listed twice"),
    ("name = 'c\nout = 'o'\n", "not valid TOML"),
]


@pytest.mark.parametrize("text,needle", BAD, ids=[needle for _, needle in BAD])
def test_a_bad_field_is_one_line_naming_it(tmp_path, text, needle):
    with pytest.raises(UsageError) as caught:
        load_campaign(write(tmp_path, text))
    message = str(caught.value)
    assert needle in message and "\n" not in message and str(tmp_path / "c.toml") in message


def test_the_command_answers_a_bad_file_with_exit_2_and_one_line(tmp_path, capsys):
    path = write(tmp_path, "name = 'c'\nout = 'o'\n[[task]]\nscene = 'lift'\nepisodes = -3\n")
    assert main(["campaign", str(path), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "episodes = -3" in err[0] and err[0].startswith("teleop campaign: error:")
    assert main(["campaign", str(tmp_path / "missing.toml")]) == 2
    assert "no such campaign file" in capsys.readouterr().err
    assert main(["campaign", str(write(tmp_path, GOOD)), "--token", "short"]) == 2
    assert "--token: a token is 8 to 128 characters" in capsys.readouterr().err
    assert main(["campaign", str(write(tmp_path, GOOD)), "--token", "same-token", "--join-token", "same-token"]) == 2
    assert "must differ" in capsys.readouterr().err


@pytest.mark.parametrize("name,ok", [
    ("Ana María", True), ("o'neil-2", True), ("x" * 64, True), ("x" * 65, False), ("", False), ("   ", False),
    ("<script>alert(1)</script>", False), ("a&b", False), ('say "hi"', False), ("_lead", False), ("x" * 10_000, False),
    (42, False),
])
def test_operator_names_are_plain_text_of_at_most_64_characters(name, ok):
    if ok:
        assert check_operator_name(name) == name.strip()
    else:
        with pytest.raises(ValueError):
            check_operator_name(name)


def test_seeds_never_repeat_across_threads_and_continue_after_a_restart(tmp_path):
    seeds: list[int] = []
    lock = threading.Lock()

    def take() -> None:
        for _ in range(10):
            seed = next_seed(tmp_path, "lift")
            with lock:
                seeds.append(seed)

    threads = [threading.Thread(target=take) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(seeds) == list(range(40))
    assert next_seed(tmp_path, "lift") == 40  # the ledger on disk is the memory: a new process continues from it
    assert next_seed(tmp_path, "stack") == 0  # per task
    assert (state_dir(tmp_path) / "seeds-lift.txt").read_text().split()[-1] == "40"


def test_episode_indices_are_reserved_past_the_files_already_there(tmp_path):
    (tmp_path / "lift").mkdir()
    (tmp_path / "lift" / "episode_000007.mcap").write_bytes(b"")  # an older run's
    assert [next_episode_index(tmp_path, "lift") for _ in range(3)] == [8, 9, 10]
    (tmp_path / "lift" / "episode_000020.hdf5").write_bytes(b"")  # written by hand meanwhile
    assert next_episode_index(tmp_path, "lift") == 21


def test_invites_are_printed_once_and_stored_hashed(tmp_path):
    tokens = issue_invites(tmp_path, ("ana", "bo"))
    assert set(tokens) == {"ana", "bo"}
    stored = json.loads((state_dir(tmp_path) / "invites.json").read_text())
    assert set(stored) == {"ana", "bo"} and all(t not in json.dumps(stored) for t in tokens.values())
    assert issue_invites(tmp_path, ("ana", "bo", "cy")).keys() == {"cy"}  # the others keep theirs
    invites = load_invites(tmp_path)
    assert invited(invites, tokens["bo"]) == "bo"
    assert invited(invites, tokens["bo"] + "x") is None and invited(invites, None) is None


def test_counts_of_an_empty_or_missing_task_folder_are_zero(tmp_path):
    count = count_task(tmp_path, "lift")
    assert (count.episodes, count.successes, count.by_operator) == (0, 0, {})
