"""End to end: `teleop run --record` a scripted pick in both formats, then replay each
file bit for bit in a fresh process."""

from __future__ import annotations

from pathlib import Path


from tests.support import PICK, run_json



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


def test_session_rows_hold_what_each_tick_did(tmp_path: Path):
    """The session fills the recorder's rows in place: each field is what that tick saw or did."""
    import mujoco
    import numpy as np

    from recorder.writer import BLOCK_ROWS
    from replay import load_episode
    from teleop import Command, Recorder, Session

    session = Session("lift", "panda", seed=2, control_hz=30)
    recorder = Recorder(session, tmp_path, ("mcap", "hdf5"), verify="off")
    recorder.start()
    site = session.controller.arms[0].site_id
    steps = BLOCK_ROWS + 40
    poses, targets, ctrls = [], [], []
    for k in range(steps):
        cmds = [Command(translation=np.array([0.0, 0.002 * np.sin(k / 9), 0.0]), source="test")] if k % 3 == 0 else []
        if k == 100:
            cmds.append(Command(gripper="close", source="test"))
        session.step(cmds)
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, session.controller.data.site_xmat[site])
        poses.append(np.concatenate([session.controller.data.site_xpos[site], quat]))
        targets.append(np.concatenate(session.controller.target_pose(0)))
        ctrls.append(session.controller.data.ctrl.copy())
    paths = recorder.save()
    nq, nv = session.controller.model.nq, session.controller.model.nv
    for path in paths:
        ep = load_episode(path)
        assert ep.steps == steps
        assert np.array_equal(ep.ee_pose[:, 0], np.array(poses)) and np.array_equal(ep.ee_target[:, 0], np.array(targets))
        assert np.array_equal(ep.ctrl, np.array(ctrls))
        assert np.array_equal(ep.time, ep.state[:, 0]) and np.array_equal(ep.qpos, ep.state[:, 1 : 1 + nq])
        assert np.array_equal(ep.qvel, ep.state[:, 1 + nq : 1 + nq + nv])
        assert np.all(np.diff(ep.time) > 0)
        assert ep.gripper[99, 0] == 1.0 and ep.gripper[100, 0] == 0.0
        assert [k for k, c in enumerate(ep.commands) if c] == sorted({*range(0, steps, 3), 100})
