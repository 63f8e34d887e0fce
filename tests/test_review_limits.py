"""Issue 48, item 4: review's limits named and checked.

Every number that decides a quality flag is a named constant in the one table
(`replay.review.quality.THRESHOLDS`), docs/review.md prints that table and the check
here fails when they differ (shown on doctored copies of the page); the jerk limit,
stated for a 30 Hz reference, flags the same motion alike at 20, 30 and 60 Hz; one pass
over the recorded states serves the success test and the contact checks.
"""

from __future__ import annotations

import ast
import dataclasses
import math
import sys

import mujoco
import numpy as np
import pytest

from replay.review import quality
from replay.review.quality import FLAGS, THRESHOLDS, ee_jerk_p90, flags, limit_rows
from replay.review.timebase import DEFAULT_CONTROL_HZ, control_dt, resample
from tests.support import ROOT, write_script

DOCS = ROOT / "docs" / "review.md"
HEADER = "| flag | score or setting | limit | unit | why |"
# Numbers quality.py's functions may write bare: none of them decides a flag (round()'s digits are not counted).
NOT_LIMITS = {
    0, 1, 2, 3,  # indices, slices, the order of a difference
    4,  # the samples a third difference needs
    6,  # mj_contactForce's 6-vector
    0.0, 1.0,  # the scores of an episode with nothing to measure
    1000.0,  # mm per m
    1e-9,  # float noise in a comparison of seconds
    25, 75,  # the quartiles that define the IQR
}


# -- the docs' table against the code's ------------------------------------------------------------


def docs_rows(markdown: str) -> list[tuple[str, str, str, str, str]]:
    """The rows of the limits table in docs/review.md: (flag, name, limit, unit, why) as written, the flag
    carried down into the setting rows that leave it blank."""
    lines = markdown.splitlines()
    try:
        start = lines.index(HEADER)
    except ValueError:
        return []
    rows, flag = [], ""
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        cells += [""] * (5 - len(cells))
        flag = cells[0].strip("`") or flag
        rows.append((flag, cells[1].strip("`"), cells[2], cells[3], " | ".join(cells[4:]).strip(" |")))
    return rows


def same_value(text: str, value: float | bool) -> bool:
    if isinstance(value, bool):
        return text == str(value).lower()
    try:
        return math.isclose(float(text), float(value), rel_tol=0, abs_tol=0)
    except ValueError:
        return False


def mismatches(markdown: str) -> list[str]:
    """Where the page's table differs from THRESHOLDS, one line each (empty: they agree)."""
    code = list(limit_rows())
    page = docs_rows(markdown)
    if not page:
        return [f"docs/review.md has no table headed {HEADER!r}"]
    out = []
    for i in range(max(len(code), len(page))):
        if i >= len(page):
            out.append(f"row {i + 1}: the code's {code[i][:2]} is missing from the page")
            continue
        if i >= len(code):
            out.append(f"row {i + 1}: the page's {page[i][:2]} is not in the code")
            continue
        (flag, name, value, unit, why), (pflag, pname, ptext, punit, pwhy) = code[i], page[i]
        where = f"row {i + 1} ({flag} {name})"
        if (pflag, pname) != (flag, name):
            out.append(f"{where}: the page has {pflag} {pname}")
        elif not same_value(ptext, value):
            out.append(f"{where}: the page's limit {ptext!r}, the code's {value!r}")
        elif punit != unit:
            out.append(f"{where}: the page's unit {punit!r}, the code's {unit!r}")
        elif pwhy != why:
            out.append(f"{where}: the page's why {pwhy!r}, the code's {why!r}")
    return out


@pytest.mark.unit
def test_the_docs_table_shows_every_limit_as_the_code_has_it():
    bad = mismatches(DOCS.read_text())
    assert not bad, "docs/review.md's limits differ from replay/review/quality.py's THRESHOLDS:\n" + "\n".join(bad)
    assert [r[0] for r in docs_rows(DOCS.read_text())].count("jerky") >= 2  # the jerk's reference rate is a row of its own


def _doctor(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


@pytest.mark.unit
@pytest.mark.parametrize("old,new,named", [
    ("| `jerk_p90` | 400 |", "| `jerk_p90` | 450 |", "jerky jerk_p90"),  # a flag's limit
    ("| `JERK_REFERENCE_HZ` | 30 |", "| `JERK_REFERENCE_HZ` | 60 |", "JERK_REFERENCE_HZ"),  # a setting
    ("| `IDLE_SPEED` | 0.01 | m/s |", "| `IDLE_SPEED` | 0.01 | cm/s |", "IDLE_SPEED"),  # a unit
    ("| `NEAR_EE` | 0.06 | m | an object this close", "| `NEAR_EE` | 0.06 | m | an object this far", "NEAR_EE"),  # a why
    ("|  | `DROP_GRACE_S` |", "|  | `DROP_WAIT_S` |", "DROP_GRACE_S"),  # a renamed row
    ("| `long` | `duration_s` | 1.5 |", "| `long` | `duration_s` | Q3 + 1.5 IQR |", "duration_s"),  # not a number
])
def test_the_check_fails_on_a_doctored_page(old, new, named):
    doctored = _doctor(DOCS.read_text(), old, new)
    bad = mismatches(doctored)
    assert len(bad) == 1 and named in bad[0], bad


@pytest.mark.unit
def test_the_check_fails_on_a_missing_or_an_extra_row():
    text = DOCS.read_text()
    row = next(line for line in text.splitlines() if "`LANDED_SPEED`" in line)
    assert any("LANDED_SPEED" in m for m in mismatches(text.replace(row + "\n", "")))
    last = next(line for line in text.splitlines() if line.startswith("| `not_exact`"))
    extra = text.replace(last, last + "\n|  | `OTHER_LIMIT` | 3 | s | a limit the code does not have |")
    assert mismatches(extra) == [f"row {len(list(limit_rows())) + 1}: the page's ('not_exact', 'OTHER_LIMIT') is not in the code"]
    assert mismatches(text.replace(HEADER, "| flag | limit |")) == [f"docs/review.md has no table headed {HEADER!r}"]


# -- the table holds every number the code decides with ----------------------------------------------


def _module_constants() -> dict[str, float]:
    """quality.py's module-level numeric constants (NAME = number)."""
    tree = ast.parse((ROOT / "replay" / "review" / "quality.py").read_text())
    out = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            name = node.targets[0].id
            if name.isupper() and isinstance(node.value, ast.Constant) and type(node.value.value) in (int, float):
                out[name] = node.value.value
    return out


@pytest.mark.unit
def test_every_constant_is_a_row_of_the_table_with_the_value_the_code_reads():
    constants = _module_constants()
    settings = {s.name: s.value for t in THRESHOLDS for s in t.settings}
    assert {name: getattr(quality, name) for name in settings} == settings  # the row holds what the code reads
    long = THRESHOLDS[FLAGS.index("long")]
    assert long.limit == quality.IQR_FENCE  # the `long` row's limit is the fence long_outliers draws
    assert set(constants) == set(settings) | {"IQR_FENCE"}, "a constant of quality.py is not in THRESHOLDS"
    for t in THRESHOLDS:
        assert t.why and (t.unit or isinstance(t.limit, bool)), t.flag
        for s in t.settings:
            assert s.why and s.unit, s.name


@pytest.mark.unit
def test_no_bare_number_decides_a_flag():
    """Outside the constants and the table, quality.py writes no number that could be a limit."""
    tree = ast.parse((ROOT / "replay" / "review" / "quality.py").read_text())
    digits = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "round" and len(node.args) == 2:
            digits.add(id(node.args[1]))
    bare = []
    for top in tree.body:
        if not isinstance(top, (ast.FunctionDef, ast.ClassDef)) or top.name in ("Setting", "Threshold"):
            continue
        for node in ast.walk(top):
            if (isinstance(node, ast.Constant) and type(node.value) in (int, float) and id(node) not in digits
                    and node.value not in NOT_LIMITS):
                bare.append(f"quality.py:{node.lineno}: {node.value!r} in {top.name}")
    assert not bare, "name these in THRESHOLDS:\n" + "\n".join(bare)


@pytest.mark.unit
def test_the_bare_number_check_can_fail():
    """The same walk finds numbers written bare as the code once wrote them (a 0.5 opening, DROP_SPEED / 5, a 1.5 s window)."""
    source = "def f(g, vz, dt):\n    return g < 0.5, vz < -DROP_SPEED / 5, round(1.5 / dt, 3)\n"
    found = [n.value for n in ast.walk(ast.parse(source)) if isinstance(n, ast.Constant) and n.value not in NOT_LIMITS]
    assert found == [0.5, 5, 1.5]


@pytest.mark.unit
def test_the_flags_read_their_limits_from_the_table():
    clean = {"idle_fraction": 0.0, "jerk_p90": 0.0, "path_ratio": 1.0, "tracking_max_mm": 0.0, "rapid_toggles": 0,
             "drops": 0, "max_contact_n": 0.0, "success": True, "bit_exact": True}
    for t in THRESHOLDS:
        if t.flag == "long":
            continue
        if isinstance(t.limit, bool):
            assert flags(dict(clean, **{t.score: t.limit})) == [t.flag]
            continue
        assert flags(dict(clean, **{t.score: t.limit})) == [], t.flag  # at the limit: not above it
        assert flags(dict(clean, **{t.score: t.limit + 1e-6})) == [t.flag]


@pytest.mark.unit
def test_long_draws_the_tables_fence():
    fence = THRESHOLDS[FLAGS.index("long")].limit
    base = {f"e{i}": ("t", s) for i, s in enumerate([10.0, 11.0, 12.0, 13.0])}
    at = 13.0 + fence * (13.0 - 11.0)  # with one more, longest of five: Q1 is 11 s, Q3 13 s
    assert quality.long_outliers(base | {"x": ("t", at + 0.01)}) == {"x"}
    assert quality.long_outliers(base | {"x": ("t", at - 0.01)}) == set()
    assert quality.long_outliers(dict(list(base.items())[:quality.IQR_MIN_EPISODES - 2]) | {"x": ("t", 1e3)}) == set()


# -- the jerk at any control rate ---------------------------------------------------------------------


def _sampled(motion, hz: float, seconds: float = 3.0) -> np.ndarray:
    """A motion along x, (T, 1, 3), sampled at `hz` from t = 0."""
    t = np.arange(0.0, seconds, 1.0 / hz)
    pos = np.zeros((len(t), 1, 3))
    pos[:, 0, 0] = motion(t)
    return pos


def _reach(t: np.ndarray) -> np.ndarray:
    """A smooth 0.3 m reach in 1.5 s (a minimum-jerk profile)."""
    s = np.clip(t / 1.5, 0.0, 1.0)
    return 0.3 * (10 * s**3 - 15 * s**4 + 6 * s**5)


def _shake(amplitude: float):
    """A 5 Hz shake of `amplitude` m (its true jerk: amplitude * (2 pi 5)^3)."""
    return lambda t: amplitude * np.sin(2 * np.pi * 5.0 * t)


MOTIONS = {  # name -> (motion, jerky or not)
    "smooth reach": (_reach, False),
    "1.6 cm shake": (_shake(0.016), False),  # differenced at 60 Hz it scored 463: flagged at 60 Hz alone
    "2.2 cm shake": (_shake(0.022), True),  # differenced at 20 Hz it scored 352: not flagged at 20 Hz alone
    "reach with a shake": (lambda t: _reach(t) + _shake(0.03)(t), True),
}


@pytest.mark.unit
@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_the_same_motion_scores_and_flags_alike_at_20_30_and_60_hz(name):
    motion, jerky = MOTIONS[name]
    limit = THRESHOLDS[FLAGS.index("jerky")].limit
    jerk = {hz: ee_jerk_p90(_sampled(motion, hz), 1.0 / hz) for hz in (20, 30, 60)}
    assert {hz: j > limit for hz, j in jerk.items()} == dict.fromkeys(jerk, jerky), jerk
    for hz in (20, 60):
        assert jerk[hz] == pytest.approx(jerk[30], rel=0.1), jerk


@pytest.mark.unit
def test_resampling_keeps_the_samples_where_the_rates_divide_and_follows_the_spline_elsewhere():
    pos = _sampled(_reach, 60)
    assert np.array_equal(resample(pos, 1 / 60, 1 / 30), pos[::2])
    assert resample(pos, 1 / 30, 1 / 30) is not None and np.array_equal(resample(pos[::2], 1 / 30, 1 / 30), pos[::2])
    coarse = _sampled(_reach, 20)
    fine = resample(coarse, 1 / 20, 1 / 30)
    truth = _sampled(_reach, 30)[:len(fine)]
    assert len(fine) == int((len(coarse) - 1) * 1.5) + 1
    assert np.abs(fine - truth).max() < 1e-4  # m: a smooth path is read back to a tenth of a millimetre
    assert np.array_equal(fine[::3], coarse[::2][:len(fine[::3])])  # where the grids meet, the samples themselves


# -- real episodes: one pass, one dt, the same flags at every rate (e2e) --------------------------------


LIFT = [
    {"duration": 1.5, "to_body": "cube", "offset": [0, 0, 0.12], "gripper": "open"},
    {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.0]},
    {"duration": 0.6, "gripper": "close"},
    {"duration": 1.2, "move": [0, 0, 0.15]},
]
JERKY = LIFT[:1] + [s for _ in range(15) for s in ({"duration": 0.1, "move": [0.03, 0, 0]},
                                                   {"duration": 0.1, "move": [-0.03, 0, 0]})] + LIFT[1:]


def _record(tmp_path, name: str, steps: list[dict], hz: float):
    import teleop
    from replay.episode import load_episode

    script = write_script(tmp_path / f"{name}.json", steps)
    session = teleop.Session(scene="lift", robot="panda", seed=0, control_hz=hz)
    with teleop.Recorder(session, tmp_path / f"{name}_{hz:g}", formats=("mcap",), verify="off") as rec:
        teleop.run_episode(session, [teleop.ScriptDevice(script)])
    return load_episode(rec.paths[0])


@pytest.mark.e2e
def test_recorded_episodes_are_flagged_jerky_alike_at_20_30_and_60_hz(tmp_path):
    from replay.review.quality import scores

    for name, steps, jerky in (("smooth", LIFT, False), ("jerky", JERKY, True)):
        seen = {}
        for hz in (20, 30, 60):
            episode = _record(tmp_path, name, steps, hz)
            assert control_dt(episode) == pytest.approx(1.0 / hz)
            s = scores(episode, exact=False)
            seen[hz] = ("jerky" in flags(s), s["jerk_p90"])
        assert all(flagged is jerky for flagged, _ in seen.values()), (name, seen)


@pytest.mark.e2e
def test_one_pass_over_the_states_serves_the_judge_and_the_contacts(tmp_path):
    from replay.judge import judge_steps
    from replay.review.quality import scores

    episode = _record(tmp_path, "lift", LIFT, 30)
    restored = 0

    def count(frame, event, arg) -> None:
        nonlocal restored
        if event == "c_call" and arg is mujoco.mj_setState:
            restored += 1

    sys.setprofile(count)
    try:
        s = scores(episode, exact=False)
    finally:
        sys.setprofile(None)
    assert restored == episode.steps  # each recorded state restored once: one pass, not one for the judge and one for contacts
    judged = judge_steps(episode)
    assert judged.any() and s["success_step"] == int(np.argmax(judged))  # the one pass judges as the judge alone does


@pytest.mark.e2e
def test_the_dt_has_one_fallback(tmp_path):
    episode = _record(tmp_path, "lift", LIFT[:1], 30)
    assert control_dt(episode) == pytest.approx(1 / 30)
    no_rate = dataclasses.replace(episode, meta=episode.meta.replace(control_hz=0.0, timestep=0.0))
    assert control_dt(no_rate) == pytest.approx(float(episode.time[1] - episode.time[0]))  # from the step times
    one_step = dataclasses.replace(no_rate, time=episode.time[:1], state=episode.state[:1])
    assert control_dt(one_step) == 1.0 / DEFAULT_CONTROL_HZ


# -- one restore loop, one atomic writer ---------------------------------------------------------------


@pytest.mark.unit
def test_review_restores_recorded_states_only_through_the_engine():
    """quality.py and video.py walk the recorded states with replay.engine.replay_states; the only mj_setState
    left in replay/review/ is the thumbnail's single state."""
    calls = {}
    for path in sorted((ROOT / "replay" / "review").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr == "mj_setState":
                calls.setdefault(path.name, []).append(node.lineno)
    assert set(calls) <= {"listing.py"} and len(calls.get("listing.py", [])) <= 1, calls
    for name in ("quality.py", "video.py"):
        assert "replay_states(" in (ROOT / "replay" / "review" / name).read_text(), name


@pytest.mark.unit
def test_a_verdict_is_written_by_the_disk_helper_whole_or_not_at_all(tmp_path):
    from recorder.disk import WriteError
    from replay.review.verdicts import read_verdict, verdict_path, write_verdict

    missing = tmp_path / "gone" / "e.mcap"
    with pytest.raises(WriteError) as caught:
        write_verdict(missing, "accept", "ana")
    assert str(caught.value).startswith(str(tmp_path / "gone")) and "\n" not in str(caught.value)
    episode = tmp_path / "e.mcap"
    write_verdict(episode, "reject", "ana", "first")
    blocked = verdict_path(episode)
    blocked.unlink()
    blocked.mkdir()  # a folder where the sidecar should go: the rename fails, the temporary file goes
    with pytest.raises(WriteError):
        write_verdict(episode, "accept", "ben")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.mcap.review.json"] and read_verdict(episode) is None
