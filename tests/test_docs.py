"""The README and docs/ cannot drift from the code: every relative link resolves (files, and headings for
#anchors), every `teleop` command and flag they name exists in the CLI's parser, and every file or folder
of the repository they name in inline code (`scenes/tasks/`, `replay/export/stats.py`) exists.

Commands are read from fenced code blocks and inline code: a line or span that starts with `teleop ` (or
`./run.sh `, which forwards to teleop; `./run.sh test` runs pytest). Flags of other programs (lerobot-train,
pytest, pip) are never read, since only what follows `teleop CMD` is. Each check has a self-test that shows
it can fail.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.support import ROOT

FENCE = re.compile(r"^(```|~~~)")
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
INLINE_CODE = re.compile(r"(`+)(.+?)\1", re.S)
PLACEHOLDER = re.compile(r"^[^a-z]|\.\.\.")  # COMMAND, ARGS..., a word that is not a command's name


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def split_code(text: str) -> tuple[list[str], str]:
    """(lines of fenced code blocks, the prose with those blocks blanked out)."""
    code, prose, inside = [], [], False
    for line in text.splitlines():
        if FENCE.match(line.strip()):
            inside = not inside
            prose.append("")
            continue
        (code if inside else prose).append(line)
        if inside:
            prose.append("")
    return code, "\n".join(prose)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped (inline code's backticks too), spaces -> '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading's anchor in a Markdown file, with GitHub's -1, -2 ... for repeats."""
    _, prose = split_code(path.read_text())
    seen: dict[str, int] = {}
    out = set()
    for line in prose.splitlines():
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match:
            base = slug(match.group(1))
            count = seen.get(base, 0)
            out.add(base if count == 0 else f"{base}-{count}")
            seen[base] = count + 1
    return out


def broken_links(path: Path) -> list[str]:
    """'file: target (why)' for every relative link in `path` that does not resolve."""
    _, prose = split_code(path.read_text())
    prose = INLINE_CODE.sub(lambda m: " " * len(m.group(0)), prose)  # `[x](y)` inside code is no link
    bad = []
    for target in LINK.findall(prose):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto: ...
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            bad.append(f"{path.name}: {target} (no such file)")
        elif anchor and (dest.suffix != ".md" or anchor not in anchors(dest)):
            bad.append(f"{path.name}: {target} (no heading '{anchor}' in {dest.name})")
    return bad


# -- commands and flags ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Mention:
    where: str
    command: str
    flags: tuple[str, ...]


def command_texts(text: str) -> list[str]:
    """Code-block lines (continuations joined, comments dropped) and inline code spans."""
    code, prose = split_code(text)
    lines, joined = [], ""
    for line in code:
        joined += line.rstrip()
        if joined.endswith("\\"):
            joined = joined[:-1] + " "
            continue
        lines.append(re.sub(r"\s#\s.*$", "", joined).strip())
        joined = ""
    spans = [" ".join(m.group(2).split()) for m in INLINE_CODE.finditer(prose)]
    return [t.strip().removeprefix("$ ") for t in lines + spans]


def mentions(text: str, where: str) -> list[Mention]:
    """Every `teleop CMD ... --flag` (and `./run.sh ...`) in the text."""
    out = []
    for line in command_texts(text):
        for part in re.split(r"\s(?:\||&&|;|\|\|)\s", line):  # `teleop scenes | head`, `a && teleop b`
            part = part.strip()
            if part.startswith("./run.sh"):
                rest = part[len("./run.sh"):].strip()
                if rest.split()[:1] == ["test"]:
                    continue  # pytest's flags
                part = "teleop " + (rest if rest and not rest.startswith("-") else f"serve --record episodes {rest}")
            if not part.startswith("teleop "):
                continue
            try:
                words = shlex.split(part)
            except ValueError:
                words = part.split()
            command = words[1] if len(words) > 1 else ""
            if PLACEHOLDER.search(command) or command.endswith(":"):  # `teleop COMMAND`, `teleop run: error: ...`
                continue
            flags = tuple(sorted({w.strip("[]()").split("=")[0] for w in words[2:] if w.strip("[]()").startswith("--")}))
            for name in command.split("|"):  # `teleop serve|run|eval --scene PATH.toml`
                out.append(Mention(where, name, flags))
    return out


def parser_commands() -> dict[str, set[str]]:
    """Every `teleop` subcommand and the option strings it accepts, from the real parser."""
    from teleop.cli.entry import build_parser

    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return {name: {o for action in p._actions for o in action.option_strings} for name, p in sub.choices.items()}


def unknown(found: list[Mention], commands: dict[str, set[str]]) -> list[str]:
    bad = []
    for m in found:
        if m.command not in commands:
            bad.append(f"{m.where}: `teleop {m.command}`: no such command")
            continue
        bad += [f"{m.where}: `teleop {m.command} {flag}`: no such flag" for flag in m.flags if flag not in commands[m.command]]
    return bad


# -- paths of the repository -------------------------------------------------------------------------------

TOP_FOLDERS = ("scenes", "teleop", "replay", "recorder", "devices", "bench", "tests", "docs", ".ci")
REPO_PATH = re.compile(r"^(?:%s)/[\w./*-]*$" % "|".join(re.escape(f) for f in TOP_FOLDERS))
GYM_ID = re.compile(r"^teleop/[\w-]+-v\d+$")  # `teleop/lift-panda-v0` is a Gymnasium id, not a path


def missing_paths(text: str, where: str, root: Path = ROOT) -> list[str]:
    """Inline-code spans that name a path under one of our folders (globs allowed) that is not there."""
    _, prose = split_code(text)
    bad = []
    for span in {" ".join(m.group(2).split()) for m in INLINE_CODE.finditer(prose)}:
        if REPO_PATH.match(span) and not GYM_ID.match(span) and not any(root.glob(span.rstrip("/"))):
            bad.append(f"{where}: `{span}` does not exist")
    return sorted(bad)


# -- the checks --------------------------------------------------------------------------------------------


def test_every_relative_link_resolves():
    bad = [line for path in pages() for line in broken_links(path)]
    assert not bad, "\n".join(bad)
    assert len(pages()) >= 10  # the README and its pages


def test_every_teleop_command_and_flag_named_exists():
    commands = parser_commands()
    found = [m for path in pages() for m in mentions(path.read_text(), path.name)]
    bad = unknown(found, commands)
    assert not bad, "\n".join(sorted(set(bad)))
    named = {m.command for m in found}
    assert {"serve", "run", "replay", "generate", "export", "eval"} <= named  # the tour's commands were read


def test_every_repository_path_named_exists():
    bad = [line for path in pages() for line in missing_paths(path.read_text(), path.name)]
    assert not bad, "\n".join(bad)


def test_the_checks_can_fail(tmp_path):
    (tmp_path / "other.md").write_text("# A page\n\n## Its `part` two\n")
    page = tmp_path / "page.md"
    page.write_text(
        "# Title\n\n[fine](other.md#its-part-two) [here](#title) [web](https://example.com)\n"
        "[gone](missing.md) [no heading](other.md#nowhere) `[not a link](missing.md)`\n"
    )
    assert broken_links(page) == [
        "page.md: missing.md (no such file)", "page.md: other.md#nowhere (no heading 'nowhere' in other.md)",
    ]
    text = (
        "```bash\nteleop run --seed 0 \\\n    --bogus 1   # a comment --also-not-read\n"
        "lerobot-train --steps=2\n./run.sh test -m unit\n./run.sh --port 9\n```\n"
        "Inline: `teleop serve|nosuch --host x`, `teleop export: error: --vary: bad`, `teleop COMMAND --x`,\n"
        "`teleop\n  replay EPISODE --verify`.\n"
    )
    found = mentions(text, "t")
    commands = {"run": {"--seed"}, "serve": {"--host", "--record"}, "replay": {"--verify"}}
    assert unknown(found, commands) == [
        "t: `teleop run --bogus`: no such flag", "t: `teleop serve --port`: no such flag", "t: `teleop nosuch`: no such command",
    ]
    assert {m.command for m in found} == {"run", "serve", "nosuch", "replay"}
    (tmp_path / "scenes" / "tasks").mkdir(parents=True)
    (tmp_path / "scenes" / "tasks" / "lift.toml").touch()
    paths = "`scenes/tasks/` `scenes/tasks/*.toml` `scenes/gone.py` `teleop.gym` `docs/<name>.md` `left/wrist` `teleop/lift-panda-v0`"
    assert missing_paths(paths, "t", root=tmp_path) == ["t: `scenes/gone.py` does not exist"]


@pytest.mark.parametrize("heading, anchor", [
    ("Cameras that see the task", "cameras-that-see-the-task"),
    ("Environments for policies (Gymnasium)", "environments-for-policies-gymnasium"),
    ("The task library, generated", "the-task-library-generated"),
    ("`teleop.gym`: the env", "teleopgym-the-env"),
])
def test_slugs_match_githubs(heading, anchor):
    assert slug(heading) == anchor


@pytest.mark.e2e  # builds and renders the lift scene three times
def test_the_workspace_frame_picture_is_drawn_on_the_real_axes(tmp_path):
    """bench/workspace_frame.py renders markers at (+0.1, 0) and (0, +0.1) in the workspace frame and stops unless
    each lands on its arrow's tip; docs/tasks.md and the README show the picture it draws."""
    out = tmp_path / "frame.png"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "PYTHONPATH": str(ROOT)}
    result = subprocess.run([sys.executable, str(ROOT / "bench" / "workspace_frame.py"), "--out", str(out)],
                            capture_output=True, text=True, env=env, timeout=300, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    miss = float(re.search(r"markers within ([0-9.]+) px", result.stdout).group(1))
    assert miss < 2.0 and out.stat().st_size > 10_000
    for page in ("README.md", "docs/tasks.md"):
        assert "workspace_frame.png" in (ROOT / page).read_text()


# -- the web folder's map ------------------------------------------------------------------------------------

ROOMS_HEADING = "## The web folder's rooms"


def rooms_map(text: str) -> dict[str, set[str]]:
    """docs/layout.md's rooms table: room folder -> the files its rows name (`a.py`, `static/x.css`)."""
    section = text.split(ROOMS_HEADING, 1)[1].split("\n## ", 1)[0]
    rooms: dict[str, set[str]] = {}
    room = ""
    for line in section.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not line.startswith("|") or set(cells[0]) <= set("-") and cells[0]:
            continue
        if cells[0].startswith("`"):
            room = cells[0].strip("`").rstrip("/")
        if room:
            rooms.setdefault(room, set()).update(m.group(2) for m in INLINE_CODE.finditer(cells[1]))
    return rooms


def rooms_on_disk(web: Path) -> dict[str, set[str]]:
    """Each sub-package of teleop/web -> its files (not __init__.py, not caches), relative to it."""
    return {
        str(folder.relative_to(web.parent.parent)): {
            str(f.relative_to(folder)) for f in folder.rglob("*")
            if f.is_file() and f.name != "__init__.py" and "__pycache__" not in f.parts}
        for folder in sorted(web.iterdir()) if folder.is_dir() and folder.name != "__pycache__"
    }


def map_differences(documented: dict[str, set[str]], tree: dict[str, set[str]]) -> list[str]:
    bad = [f"{room}/ is not in docs/layout.md's rooms" for room in sorted(set(tree) - set(documented))]
    bad += [f"{room}/ in docs/layout.md is not a folder" for room in sorted(set(documented) - set(tree))]
    for room in sorted(set(tree) & set(documented)):
        bad += [f"{room}/{name} is not in docs/layout.md" for name in sorted(tree[room] - documented[room])]
        bad += [f"{room}/{name} in docs/layout.md does not exist" for name in sorted(documented[room] - tree[room])]
    return bad


def test_the_web_folders_map_matches_the_tree():
    documented = rooms_map((ROOT / "docs" / "layout.md").read_text())
    tree = rooms_on_disk(ROOT / "teleop" / "web")
    assert {"teleop/web/session_page", "teleop/web/shared", "teleop/web/viser_internals"} <= set(tree)
    flat = sorted(p.name for p in (ROOT / "teleop" / "web").iterdir() if p.is_file() and p.name != "__init__.py")
    assert not flat, f"teleop/web/ keeps its modules in rooms, not flat: {flat}"
    bad = map_differences(documented, tree)
    assert not bad, "\n".join(bad)


def test_the_map_check_can_fail(tmp_path):
    web = tmp_path / "teleop" / "web"
    (web / "room").mkdir(parents=True)
    (web / "room" / "a.py").write_text("")
    (web / "room" / "b.js").write_text("")
    (web / "other").mkdir()
    text = f"{ROOMS_HEADING}\n\n| room | module | holds |\n|---|---|---|\n| `teleop/web/room/` | `a.py` | a |\n| | `c.py` | c |\n"
    bad = map_differences(rooms_map(text), rooms_on_disk(web))
    assert bad == ["teleop/web/other/ is not in docs/layout.md's rooms", "teleop/web/room/b.js is not in docs/layout.md",
                   "teleop/web/room/c.py in docs/layout.md does not exist"]
