"""Issue 37: two-arm generation. Each arm runs its own segments in parallel; a sequential constraint makes
an arm wait; a coordinated pair shares one source and one transform and ends on the same tick.

Sources are the tasks' scripts recorded on seeds 0-2 with the bimanual robot; generation uses new seeds (1000+).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import teleop
from replay.subtasks.sidecar import by_arm, read_subtasks
from scenes.tasks.registry import find_task
from teleop.control.loop import run_episode
from teleop.generate.arms import ArmsPlanDevice, choose_arm_segments
from teleop.generate.generator import GenerateOptions, generate, load_sources
from tests.support import ROOT, run_json

pytestmark = pytest.mark.e2e


def _record(scene: str | Path, directory: Path, script: Path, seeds=(0, 1, 2)) -> list[Path]:
    paths = []
    for seed in seeds:
        session = teleop.Session(scene=str(scene), robot="bimanual", seed=seed, control_hz=30)
        with teleop.Recorder(session, directory, verify="off") as rec:
            assert teleop.run_episode(session, [teleop.ScriptDevice(script)]).success
        paths.extend(rec.paths)
    return paths


def _script(task: str) -> Path:
    return find_task(task).script_for("bimanual")


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> dict[str, list[Path]]:
    root = tmp_path_factory.mktemp("two_arm_sources")
    out = {task: _record(task, root / task, _script(task)) for task in ("handover", "lift_tray", "two_cubes_two_bins")}
    # two_cubes_two_bins with one constraint more: the right arm's grasp waits until the left arm has placed its cube
    text = (ROOT / "scenes" / "library" / "two_cubes_two_bins.toml").read_text().replace('script = "../scripts/two_cubes_two_bins.json"\n', "")
    text = text.replace('name = "two_cubes_two_bins"', 'name = "two_cubes_in_turn"')
    text = text.replace("\n[[object]]", '\n[[constraint]]\nkind = "sequential"\nfirst = ["left", 1]\nthen = ["right", 0]\n\n[[object]]', 1)
    (root / "in_turn.toml").write_text(text)
    out["in_turn"] = _record(root / "in_turn.toml", root / "in_turn", _script("two_cubes_two_bins"), seeds=(0, 1))
    return out


def _moving(ep, arm: int) -> np.ndarray:
    """Ticks t at which the arm's EE target differs from tick t - 1."""
    return np.nonzero(np.any(np.abs(np.diff(ep.ee_target[:, arm], axis=0)) > 1e-9, axis=1))[0] + 1


def _generate(paths, out: Path, num: int, **kw):
    summary = generate(paths, GenerateOptions(out=out, num=num, seed=1000, workers=2, max_attempts=num, progress=False, **kw))
    assert summary.not_bit_exact == 0
    episodes = [teleop.load_episode(f) for f in summary.files]
    for ep in episodes:  # every generated episode replays bit for bit, and comes annotated per arm
        assert ep.meta.source == "generated" and ep.meta.success and teleop.resimulate(ep).bit_exact
        assert set(by_arm(read_subtasks(ep.path, ep.steps))) == {"left", "right"}
    return summary, episodes


def test_handover_generates_with_the_right_arm_waiting_for_the_left_arms_lift(sources, tmp_path):
    summary, episodes = _generate(sources["handover"], tmp_path / "gen", 10)
    assert summary.success_rate >= 0.7, summary
    for ep in episodes:
        arms = by_arm(read_subtasks(ep.path, ep.steps))
        exchange = arms["left"][1].start  # the left arm's lift has ended: the exchange (coordinated) begins for both
        assert arms["right"][0].start == 0 and exchange > 30
        moving = _moving(ep, 1)
        assert moving.min() >= exchange, (moving.min(), exchange)  # the right arm held still until then
        gen = ep.meta.generator
        assert gen["arms"]["left"]["subtasks"] == ["cube", "world"] and gen["arms"]["right"]["subtasks"] == ["cube"]
        assert len(set(gen["sources"])) == 1  # shared by default: one source episode for both arms


def test_arms_run_in_parallel_and_a_sequential_constraint_keeps_the_second_waiting(sources, tmp_path):
    _, parallel = _generate(sources["two_cubes_two_bins"], tmp_path / "parallel", 3)
    _, in_turn = _generate(sources["in_turn"], tmp_path / "in_turn", 3)
    for ep in parallel:  # no constraint: both arms start at once
        assert _moving(ep, 0).min() <= 2 and _moving(ep, 1).min() <= 2
    for ep in in_turn:  # the right arm's grasp starts only once the left arm's place has ended (its last move)
        left_done = _moving(ep, 0).max()
        assert _moving(ep, 1).min() > left_done, (_moving(ep, 1).min(), left_done)
        assert by_arm(read_subtasks(ep.path, ep.steps))["right"][1].start > left_done
    assert min(e.steps for e in in_turn) > max(e.steps for e in parallel) + 60  # waiting costs time


@pytest.mark.parametrize("task,pair", [("lift_tray", ((0, 0), (1, 0))), ("handover", ((0, 1), (1, 0)))])
def test_a_coordinated_pair_begins_and_ends_on_the_same_tick(task, pair, sources):
    job, _ = load_sources(sources[task])
    for seed in (1000, 1001):
        session = job.session(seed)
        chosen = choose_arm_segments(session, [s.arms for s in job.sources], job.constraints,
                                     np.random.default_rng(seed), per_arm=False)
        device = ArmsPlanDevice(session, chosen, job.constraints)
        result = run_episode(session, [device], max_steps=job.max_steps)
        assert result.success
        (a, i), (b, j) = pair
        assert device.spans[a][i] == device.spans[b][j], device.spans
        assert device.spans[a][i][1] > device.spans[a][i][0] + 30
        # one source episode for the whole pair
        assert chosen[a][i].source == chosen[b][j].source


def test_source_per_arm_from_the_command_line(sources, tmp_path):
    out = run_json("generate", *map(str, sources["two_cubes_two_bins"]), "--out", str(tmp_path / "gen"), "--num", "2",
                   "--seed", "1000", "--workers", "1", "--source-per-arm", "--json")
    assert out["successes"] == 2 and len(out["files"]) == 2
    gen = teleop.load_episode(out["files"][0]).meta.generator
    assert gen["source_per_arm"] is True and set(gen["arms"]) == {"left", "right"}
    assert not any(p.name.endswith(".part") for p in (tmp_path / "gen").iterdir())


def test_a_one_arm_task_is_generated_as_before(tmp_path):
    session = teleop.Session(scene="lift", robot="panda", seed=0, control_hz=30)
    with teleop.Recorder(session, tmp_path / "src", verify="off") as rec:
        teleop.run_episode(session, [teleop.ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")])
    summary = generate(rec.paths, GenerateOptions(out=tmp_path / "gen", num=2, seed=1000, workers=1, progress=False))
    assert summary.successes == 2
    ep = teleop.load_episode(summary.files[0])
    assert set(ep.meta.generator) == {"name", "version", "seed", "subtasks", "sources", "settle_s"}  # no per-arm keys
    assert not list((tmp_path / "gen").glob("*.subtasks.json"))
