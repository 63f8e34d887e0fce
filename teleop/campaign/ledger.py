"""What a campaign knows from disk: seeds handed out, episodes counted, invite tokens.

Everything lives under the campaign's `out/` folder, so a restart continues where
the last run stopped:
- `out/<task>/episode_*.mcap|hdf5`: the episodes; counts are read from them
  (successful episodes per task and per operator, and when each was recorded: the
  admin page's episodes per hour), never kept on the side;
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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime
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
    # (when it started: Unix time, s; its operator or None) of each successful episode, the admin page's plot
    success_times: list[tuple[float, str | None]] = field(default_factory=list)


Facts = tuple[int, bool, str | None, str | None, float]  # seed, success, operator, session, start (Unix time, s)
_facts_cache: dict[str, tuple[tuple[int, int], Facts]] = {}


def started_at(start_time: str, fallback: float) -> float:
    """An episode's recorded start (EpisodeMeta.start_time, ISO 8601) as Unix time in seconds; `fallback` (the
    file's modification time) for a file that has none or an unreadable one."""
    try:
        stamp = datetime.fromisoformat(start_time)
    except (TypeError, ValueError):
        return fallback
    return stamp.timestamp() if stamp.tzinfo is not None else fallback  # no zone: not ours, do not guess one


def _facts(path: Path, settle: bool = True) -> Facts | None:
    """(seed, success, operator, session, start) of one episode file, cached while its size and time stay.

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
    facts = (meta.seed, meta.success, meta.operator, meta.session, started_at(meta.start_time, st.st_mtime))
    _facts_cache[str(path)] = (stamp, facts)
    return facts


def _episode_facts(folder: Path, settle: bool = True) -> list[Facts]:
    if not folder.is_dir():
        return []
    return [f for p in find_episodes([folder]) if (f := _facts(p, settle)) is not None]


def count_task(out: Path, task: str, settle: bool = True) -> TaskCount:
    """What out/<task>/ holds now (`settle=False`: files written a moment ago too)."""
    count = TaskCount()
    for _, success, operator, session, start in _episode_facts(Path(out) / task, settle):
        count.episodes += 1
        count.successes += int(success)
        if success:
            count.success_times.append((start, operator))
        for key, table in ((operator, count.by_operator), (session, count.by_session)):
            if key:
                mine = table.setdefault(key, [0, 0])
                mine[0] += 1
                mine[1] += int(success)
    return count


HOUR_S = 3600.0
MAX_HOURS = 24 * 14  # the plot's span at most: the last two weeks


def hourly_successes(counts: Mapping[str, TaskCount], now: float | None = None, max_hours: int = MAX_HOURS) -> dict:
    """Successful episodes per hour, from each one's recorded start: for the campaign, per operator and per task.

    {"start": Unix time (s) of the first hour, "hour_s": 3600, "now": Unix time, "campaign": [n per hour],
    "operators": {name: [n per hour]}, "tasks": {name: [n per hour]}}; hours run from the one of the first
    successful episode (at most `max_hours` back) to the current one, on whole UTC hours. Episodes without an
    operator count for the campaign and their task only.
    """
    now = time.time() if now is None else float(now)
    last = int(now // HOUR_S)
    times = [(t, op, task) for task, count in counts.items() for t, op in count.success_times]
    first = max(min((int(t // HOUR_S) for t, _, _ in times), default=last), last - max_hours + 1)
    first = min(first, last)
    n = last - first + 1
    campaign = [0] * n
    operators: dict[str, list[int]] = {}
    tasks: dict[str, list[int]] = {task: [0] * n for task in counts}
    for t, operator, task in times:
        i = int(t // HOUR_S) - first
        if not 0 <= i < n:  # older than the span, or a clock ahead of this machine's
            continue
        campaign[i] += 1
        tasks[task][i] += 1
        if operator:
            operators.setdefault(operator, [0] * n)[i] += 1
    return {"start": first * HOUR_S, "hour_s": HOUR_S, "now": now, "campaign": campaign,
            "operators": dict(sorted(operators.items())), "tasks": tasks}


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
