"""Issue 36: `teleop export` of what passed review, with the verdicts, flags and subtasks in the dataset.

Three short lift recordings at 15 Hz: two scripted picks (the first annotated with subtasks) and
one that lifts the cube and lets it go in the air (flagged `dropped` and `failed`). Reviewed by
their sidecars, as the review page writes them.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from replay.review.verdicts import write_verdict
from tests.support import PICK, assert_one_line_error, column, open_dataset, record_script, run_cli, run_json, run_main, write_script

os.environ["HF_HUB_OFFLINE"] = "1"  # nothing may be downloaded, ever
HZ = "15"
DROP = [
    {"duration": 1.5, "to_body": "cube", "offset": [0, 0, 0.12], "gripper": "open"},
    {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.0]},
    {"duration": 0.6, "gripper": "close"},
    {"duration": 1.2, "move": [0, 0, 0.15]},
    {"duration": 0.3, "gripper": "open"},
    {"duration": 1.5},
]


@pytest.fixture(scope="module")
def reviewed(tmp_path_factory):
    root = tmp_path_factory.mktemp("reviewed")
    folder = root / "eps"
    record_script(folder, PICK, "--control-hz", HZ, "--episodes", "2")
    record_script(folder, write_script(root / "drop.json", DROP), "--control-hz", HZ, "--seed", "5")
    files = sorted(folder.glob("*.mcap"))
    assert len(files) == 3
    run_json("annotate", str(files[0]), "--auto", "--json")
    write_verdict(files[0], "accept", "ana", "clean")
    write_verdict(files[1], "reject", "ben", "slow")
    write_verdict(files[2], "accept", "ana")
    return {"dir": folder, "files": files, "root": root}


def episodes_table(out):
    import pandas as pd

    return pd.concat([pd.read_parquet(p) for p in sorted((out / "meta" / "episodes").rglob("*.parquet"))])


@pytest.mark.e2e
def test_export_accepted_leaves_out_the_rest_and_says_why(reviewed):
    out = reviewed["root"] / "accepted"
    result = run_cli("export", str(reviewed["dir"]), "--out", str(out), "--repo-id", "test/accepted", "--accepted",
                     "--image-size", "32x32", "--cameras", "front")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "exported 2 episodes" in result.stdout and "skipped 1 not accepted" in result.stdout
    table = episodes_table(out)
    assert list(table["review_verdict"]) == ["accept", "accept"] and list(table["review_reviewer"]) == ["ana", "ana"]
    flags = [json.loads(f) for f in table["review_flags"]]
    assert flags[0] == [] and "dropped" in flags[1] and "failed" in flags[1]
    # subtasks, LeRobot's way: meta/subtasks.parquet (text as the index) and a per-frame subtask_index
    import pandas as pd

    subtasks = pd.read_parquet(out / "meta" / "subtasks.parquet")
    assert subtasks.index.name == "subtask" and list(subtasks["subtask_index"]) == list(range(len(subtasks)))
    annotation = json.loads((reviewed["files"][0].parent / (reviewed["files"][0].name + ".subtasks.json")).read_text())
    names = list(subtasks.index)
    ds = open_dataset(out, "test/accepted")
    ids = column(ds, "subtask_index").reshape(-1)
    episode = column(ds, "episode_index").reshape(-1)
    first = ids[episode == 0]
    expected = np.concatenate([[names.index(s["object"])] * (s["end"] - s["start"]) for s in annotation["subtasks"]])
    assert np.array_equal(first, expected)
    assert (ids[episode == 1] == -1).all()  # no annotations: -1


@pytest.mark.e2e
def test_reject_flags_leave_out_the_flagged_and_a_bad_flag_is_one_line(reviewed):
    out = reviewed["root"] / "clean"
    result = run_cli("export", str(reviewed["dir"]), "--out", str(out), "--repo-id", "test/clean", "--accepted",
                     "--reject-flags", "dropped,idle", "--image-size", "32x32", "--cameras", "none")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "exported 1 episode," in result.stdout
    assert "1 not accepted" in result.stdout and "1 flagged dropped" in result.stdout
    assert list(episodes_table(out)["review_verdict"]) == ["accept"]
    bad = run_main("export", str(reviewed["dir"]), "--out", str(reviewed["root"] / "x"), "--repo-id", "t/x",
                   "--reject-flags", "wobbly")  # in this process
    assert_one_line_error(bad, "--reject-flags wobbly", "not a quality flag", "dropped")
    assert not (reviewed["root"] / "x").exists()
