"""The "Scripting" example of docs/scripting.md runs verbatim, and `import teleop` offers what it promises."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

import teleop
from tests.support import ROOT

PUBLIC = (
    "Session", "ScriptDevice", "Recorder", "run_episode", "load_episode", "resimulate", "export_lerobot", "serve",
    "Command", "Controller", "EpisodeMeta", "KeyboardDevice", "SpaceMouseDevice", "GizmoDevice", "replay_states",
    "TeleopError",
)


def readme_example() -> str:
    text = (ROOT / "docs" / "scripting.md").read_text()
    section = text.split("\n## Scripting\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert blocks, "docs/scripting.md's Scripting section has no python block"
    return blocks[0]


def test_public_names_are_documented():
    for name in PUBLIC:
        obj = getattr(teleop, name)
        assert obj.__doc__ and obj.__doc__.strip(), f"teleop.{name} has no docstring"


def test_import_teleop_and_the_command_line_load_no_physics_until_asked():
    """`import teleop` and `teleop --help` (every command's parser) stay quick: MuJoCo, mink and LeRobot load with
    the first name that needs them; then every public name is there, in dir() too."""
    code = ("import sys, teleop, teleop.cli.entry as e; e.build_parser(); "
            "heavy = sorted(m for m in ('mujoco', 'mink', 'scipy', 'lerobot', 'torch', 'viser') if m in sys.modules); "
            "print(heavy); teleop.Session; print('mujoco' in sys.modules, sorted(set(teleop.__all__) - set(dir(teleop))))")
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["[]", "True []"], out.stdout
    with pytest.raises(AttributeError, match="no attribute 'Sesion'"):
        teleop.Sesion  # noqa: B018 - a misspelt name is an AttributeError, not a KeyError or an import


@pytest.mark.e2e  # records, then exports through LeRobot, in a fresh interpreter
def test_readme_example_runs_verbatim(tmp_path):
    (tmp_path / "scenes").symlink_to(ROOT / "scenes")
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    result = subprocess.run(
        [sys.executable, "-c", readme_example()], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    first = result.stdout.splitlines()[0].split()
    assert first[0] == "True" and int(first[1]) > 50  # the scripted pick succeeded
    files = sorted(p.name for p in (tmp_path / "episodes").iterdir())
    assert files == ["episode_000000.hdf5", "episode_000000.mcap"]
    episode = teleop.load_episode(tmp_path / "episodes" / "episode_000000.hdf5")
    assert isinstance(episode.meta, teleop.EpisodeMeta)
    assert episode.meta.success and episode.meta.complete and episode.meta.source == "script"
    assert episode.meta.devices == ("script:lift_pick.json",)
    assert (tmp_path / "datasets" / "lift" / "meta" / "info.json").is_file()


def test_recorder_keeps_an_episode_cut_short_by_an_exception(tmp_path):
    session = teleop.Session(scene="lift", robot="panda", seed=3, control_hz=30)
    try:
        with teleop.Recorder(session, tmp_path, verify="off") as rec:
            teleop.run_episode(session, [], max_steps=5, record=False)
            rec.start()
            for _ in range(7):
                session.step([teleop.Command(translation=[0.0, 0.0, 0.001])])
            raise RuntimeError("the user's script failed")
    except RuntimeError:
        pass
    assert len(rec.paths) == 1 and session.recorder is None
    episode = teleop.load_episode(rec.paths[0])
    assert episode.steps == 7 and not episode.meta.complete
    assert teleop.resimulate(episode).bit_exact


@pytest.mark.e2e  # a LeRobot export (the first import of LeRobot alone takes seconds)
def test_export_lerobot_takes_the_options_object(tmp_path):
    """Every export option reaches `teleop.export_lerobot`: the options object, its fields as keywords
    (which win over it), and nothing else."""
    with pytest.raises(TypeError, match="worker"):
        teleop.export_lerobot([], out=tmp_path / "x", repo_id="t/x", worker=2)
    session = teleop.Session(scene="lift", robot="panda", seed=0, control_hz=30)
    with teleop.Recorder(session, tmp_path / "episodes", verify="off") as rec:
        teleop.run_episode(session, [], max_steps=6)
    options = teleop.ExportOptions(out=tmp_path / "unused", repo_id="t/unused", cameras=["front"], object_state=False,
                                   progress=False)
    summary = teleop.export_lerobot(rec.paths, tmp_path / "ds", "t/ds", options=options, cameras=[], video=False)
    features = json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())["features"]
    assert summary.episodes == 1 and summary.frames == 6 and summary.cameras == []
    assert "observation.environment_state" not in features  # from the options object
    assert not any(key.startswith("observation.images") for key in features)  # the keyword won
    assert not (tmp_path / "unused").exists()
