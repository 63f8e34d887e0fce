"""What a campaign knows from disk: seeds handed out, episodes counted, invite tokens.

Everything lives under the campaign's `out/` folder, so a restart continues where
the last run stopped:
- `out/<task>/episode_*.mcap|hdf5`: the episodes; counts are read from them
  (successful episodes per task and per operator), never kept on the side;
- `out/.campaign/seeds-<task>.txt`: every seed handed out for the task, one a line,
  appended under an exclusive lock by whichever session process asks, so seeds
  never repeat within a task across operators and restarts;
- `out/.campaign/invites.json`: {operator: sha256 of their invite token}; the
  tokens themselves are printed once and not stored.
"""

from __future__ import annotations

import fcntl
import hashlib
import hmac
import json
import os
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from recorder.writer import next_episode_index as next_index_in
from replay.episode import EpisodeError, find_episodes, load_episode
from teleop.errors import UsageError

STATE_DIR = ".campaign"
SETTLE_S = 1.5  # a file changed more recently than this is being written: counted once it settles


def state_dir(out: Path) -> Path:
    """The campaign's own files inside out/ (seeds, invites, session logs)."""
    return Path(out) / STATE_DIR


def _reserve(path: Path, floor: Callable[[], int]) -> int:
    """Append and return one past the highest number in the ledger file at `path`, and at least `floor()`,
    under an exclusive lock (so processes never get the same number)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)  # released when the file closes
        f.seek(0)
        seen = [int(word) for word in f.read().split() if word.lstrip("-").isdigit()]
        number = max(max(seen, default=-1) + 1, floor())
        f.write(f"{number}\n")
        f.flush()
        os.fsync(f.fileno())
    return number


def next_seed(out: Path, task: str) -> int:
    """Reserve the task's next seed: one past the highest ever handed out (or recorded on disk)."""
    path = state_dir(out) / f"seeds-{task}.txt"
    folder = Path(out) / task

    def on_disk() -> int:  # a first run, or a lost ledger: never below the seeds already recorded
        return 0 if path.exists() and path.stat().st_size else max((f[0] for f in _episode_facts(folder)), default=-1) + 1

    return _reserve(path, on_disk)


def next_episode_index(out: Path, task: str) -> int:
    """Reserve the index of the task's next episode file: sessions recording into one folder at once
    never pick the same `episode_NNNNNN` (the recorder's own choice looks at the folder, not at the others)."""
    return _reserve(state_dir(out) / f"episodes-{task}.txt", lambda: next_index_in(Path(out) / task))


# -- counts from the episode files -------------------------------------------------

@dataclass
class TaskCount:
    """Episodes of one task on disk: all, successful, and both per operator."""

    episodes: int = 0
    successes: int = 0
    by_operator: dict[str, list[int]] = field(default_factory=dict)  # operator -> [episodes, successes]
    by_session: dict[str, list[int]] = field(default_factory=dict)  # session id -> [episodes, successes]


Facts = tuple[int, bool, str | None, str | None]  # seed, success, operator, session
_facts_cache: dict[str, tuple[tuple[int, int], Facts]] = {}


def _facts(path: Path, settle: bool = True) -> Facts | None:
    """(seed, success, operator, session) of one episode file, cached while its size and time stay.

    A file written to in the last SETTLE_S is not read (None): it is an episode being recorded, whose
    outcome is not in it yet, and reading every growing file at every count would cost each session
    more than its recording does. `settle=False` reads it anyway (an episode just saved).
    """
    try:
        st = path.stat()
    except OSError:
        return None
    stamp = (st.st_mtime_ns, st.st_size)
    cached = _facts_cache.get(str(path))
    if cached is not None and cached[0] == stamp:
        return cached[1]
    if settle and time.time() - st.st_mtime < SETTLE_S:
        return None
    try:
        meta = load_episode(path).meta
    except (EpisodeError, OSError):  # being written (no metadata yet) or broken: not counted
        return None
    facts = (meta.seed, meta.success, meta.operator, meta.session)
    _facts_cache[str(path)] = (stamp, facts)
    return facts


def _episode_facts(folder: Path, settle: bool = True) -> list[Facts]:
    if not folder.is_dir():
        return []
    return [f for p in find_episodes([folder]) if (f := _facts(p, settle)) is not None]


def count_task(out: Path, task: str, settle: bool = True) -> TaskCount:
    """What out/<task>/ holds now (`settle=False`: files written a moment ago too)."""
    count = TaskCount()
    for _, success, operator, session in _episode_facts(Path(out) / task, settle):
        count.episodes += 1
        count.successes += int(success)
        for key, table in ((operator, count.by_operator), (session, count.by_session)):
            if key:
                mine = table.setdefault(key, [0, 0])
                mine[0] += 1
                mine[1] += int(success)
    return count


# -- invite tokens -------------------------------------------------------------------

def _digest(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8", "replace")).hexdigest()


def load_invites(out: Path) -> dict[str, str]:
    """{operator: token digest} stored so far."""
    path = state_dir(out) / "invites.json"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        raise UsageError(f"{path}: unreadable invite list ({exc}); delete it to issue new invites") from None
    return {str(k): str(v) for k, v in data.items()} if isinstance(data, dict) else {}


def issue_invites(out: Path, operators: tuple[str, ...]) -> dict[str, str]:
    """New invite tokens for the operators that have none yet ({operator: token}); stores their digests."""
    stored = load_invites(out)
    new = {name: secrets.token_urlsafe(18) for name in operators if name not in stored}
    if new:
        stored.update({name: _digest(token) for name, token in new.items()})
        path = state_dir(out) / "invites.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(stored, indent=1, sort_keys=True))
        os.chmod(tmp, 0o600)
        os.replace(tmp, path)
    return new


def invited(invites: dict[str, str], token: str | None) -> str | None:
    """The operator whose invite `token` is, or None."""
    if not token:
        return None
    digest = _digest(token)
    return next((name for name, d in invites.items() if hmac.compare_digest(d, digest)), None)
