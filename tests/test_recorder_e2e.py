"""End to end: `teleop run --record` a scripted pick in both formats, then replay each
file bit for bit in a fresh process."""

from __future__ import annotations

from pathlib import Path


from tests.conftest import ROOT, run_json

PICK = ROOT / "scenes" / "scripts" / "lift_pick.json"


def test_recorded_pick_replays_bit_exact_in_fresh_processes(tmp_path: Path):
    out = run_json("run", "--device", f"script:{PICK}", "--scene", "lift", "--robot", "panda", "--seed", "4",
                   "--episodes", "2", "--record", str(tmp_path), "--format", "both", "--json")
    files = sorted(tmp_path.iterdir())
    assert [f.name for f in files] == [f"episode_00000{i}.{s}" for i in (0, 1) for s in ("hdf5", "mcap")]
    assert sorted(out["files"]) == [str(f) for f in files]
    for path in files:
        info = run_json("inspect", str(path), "--json")
        assert info["scene"] == "lift" and info["robot"] == "panda" and info["seed"] == 4 + int(path.stem[-1])
        assert info["complete"] is True and info["truncated"] is False and info["steps"] > 100
        assert info["success"] is True  # the script lifts the cube
        verdict = run_json("replay", str(path), "--verify", "--json")
        assert verdict["bit_exact"] is True and verdict["first_divergence_step"] is None
        assert verdict["steps"] == info["steps"] and verdict["warnings"] == []


def test_failed_episode_is_kept_and_marked(tmp_path: Path):
    run_json("run", "--device", f"script:{PICK}", "--scene", "lift", "--seconds", "0.5",
             "--record", str(tmp_path), "--format", "mcap", "--json")
    info = run_json("inspect", str(tmp_path / "episode_000000.mcap"), "--json")
    assert info["success"] is False and info["complete"] is True and info["steps"] == 15
