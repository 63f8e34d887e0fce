"""Generation that continues where it stopped: which seeds an --out already holds, and a journal of them.

A run's attempts are taken in seed order (seed S+i is attempt i and its files carry
episode index base+i), so a run killed at any point has done a prefix of its seeds.
`--out` holds a journal, `.generate.jsonl`: a first line naming the run (sources,
seed, formats, whether failures are kept, the first episode index), written
atomically, then one line per attempt taken, appended after the attempt's files
have landed (each file written as NAME.part, then renamed).

A re-run with the same sources and options reads it and decides by the files: a
seed is done when its episode files are all there (whatever the journal says: a
kill -9 between the rename and the journal line loses nothing), or when the journal
records it as failed. Files of a seed only partly there (one format of two) and
`*.part` files are removed; the seed is run again, and gives the same bytes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from recorder.disk import remove_parts, write_error, write_text_whole
from replay.episode import EpisodeError, load_episode
from scenes.errors import TeleopError

JOURNAL = ".generate.jsonl"
FORMAT = 1
SAME = ("generator_version", "sources", "subtasks", "seed", "formats", "keep_failures", "variation",
        "source_per_arm")  # a resume must share these


class ResumeRefused(TeleopError, ValueError):
    """--out holds other work than this run's (one line naming what differs)."""


def run_identity(sources: Sequence[Any], seed: int, formats: Sequence[str], keep_failures: bool,
                 version: int) -> dict:
    """What a resume must share with the run it continues: the sources (paths and what generation takes
    from them: the segments' poses, gripper commands and objects), the first seed, formats, failures kept."""
    digest = hashlib.sha256()
    for src in sources:
        for seg in src.segments:
            digest.update(seg.object.encode())
            for array in (seg.poses, seg.gripper_open, seg.object_pose):
                digest.update(array.tobytes())
    return {"generator_version": version, "sources": [str(Path(s.name).resolve()) for s in sources],
            "subtasks": digest.hexdigest(), "seed": seed, "formats": list(formats), "keep_failures": keep_failures}


def _episode_files(directory: Path) -> dict[int, list[Path]]:
    out: dict[int, list[Path]] = {}
    if directory.is_dir():
        for path in sorted(directory.glob("episode_*")):
            stem, _, suffix = path.name.partition(".")
            if suffix in ("mcap", "hdf5") and stem[8:].isdigit():
                out.setdefault(int(stem[8:]), []).append(path)
    return out


@dataclass
class Done:
    """What --out already holds of this run."""

    base: int  # episode index of seed offset 0
    kept: dict[int, list[str]] = field(default_factory=dict)  # seed -> files of a kept success
    failed: dict[int, list[str]] = field(default_factory=dict)  # seed -> files kept in failures/ (may be none)
    removed: list[str] = field(default_factory=list)  # partial files removed

    @property
    def seeds(self) -> set[int]:
        return set(self.kept) | set(self.failed)


class Journal:
    """The run's journal in --out: opened (and checked) before any work, a line appended per attempt taken."""

    def __init__(self, out: Path, identity: dict, force_new: bool = False,
                 log: Callable[[str], None] | None = None) -> None:
        self.out = Path(out)
        self.path = self.out / JOURNAL
        self.identity = identity
        self.log = log or (lambda line: None)
        self.done = self._open(force_new)

    # -- reading ------------------------------------------------------------------

    def _read(self) -> tuple[dict | None, list[dict]]:
        try:
            lines = self.path.read_text().splitlines()
        except FileNotFoundError:
            return None, []
        except OSError as exc:
            raise write_error(self.path, exc) from None
        records = []
        for line in lines:
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line cut by a kill: that attempt's files decide
        header = records[0] if records and records[0].get("format") == FORMAT else None
        return header, records[1:] if header else []

    def _open(self, force_new: bool) -> Done:
        header, attempts = self._read()
        files = {**_episode_files(self.out), **{-1 - i: p for i, p in _episode_files(self.out / "failures").items()}}
        same = header is not None and all(header.get(k) == self.identity.get(k) for k in SAME)
        if header is not None and same and not force_new:
            return self._resume(header["base"], attempts)
        if (files or attempts) and not force_new:
            if header is None:
                raise ResumeRefused(f"{self.out} already holds {len(files)} episodes that no generate run recorded "
                                    f"there; choose another --out, or add --force-new to add a new run beside them")
            differ = [k for k in SAME if header.get(k) != self.identity.get(k)]
            raise ResumeRefused(f"{self.out} holds a generate run with other {', '.join(_words(differ))}; run it "
                                f"again with the same ones to resume it, choose another --out, or add --force-new")
        return self._start()

    def _start(self) -> Done:
        """A new run: the first episode index after everything there, the header written atomically."""
        from recorder import next_episode_index

        self.out.mkdir(parents=True, exist_ok=True)
        base = max(next_episode_index(self.out), next_episode_index(self.out / "failures"))
        header = {"format": FORMAT, **self.identity, "base": base}
        write_text_whole(self.path, json.dumps(header) + "\n")
        return Done(base=base)

    def _resume(self, base: int, attempts: list[dict]) -> Done:
        done = Done(base=base)
        for directory in (self.out, self.out / "failures"):
            done.removed += [str(p) for p in remove_parts(directory)]
        seed0 = self.identity["seed"]
        journaled = {int(a["seed"]): a for a in attempts if "seed" in a}
        wanted = self.identity["formats"]
        for directory, kept in ((self.out, True), (self.out / "failures", False)):
            for index, paths in _episode_files(directory).items():
                if index < base:
                    continue  # an earlier run's (before a --force-new)
                seed = seed0 + index - base
                entry = journaled.get(seed)
                if entry is None and not self._is_ours(paths[0], seed):
                    continue  # not this run's file: left alone
                if sorted(p.suffix[1:] for p in paths) != sorted(wanted):  # killed between its formats
                    for path in paths:
                        with contextlib.suppress(OSError):
                            path.unlink()
                        done.removed.append(str(path))
                    continue
                (done.kept if kept else done.failed)[seed] = [str(p) for p in paths]
        for seed, entry in journaled.items():
            if not entry.get("success") and seed not in done.kept:
                done.failed.setdefault(seed, [])
        if done.removed:
            self.log(f"removed {len(done.removed)} partly written files: {', '.join(Path(p).name for p in done.removed)}")
        return done

    @staticmethod
    def _is_ours(path: Path, seed: int) -> bool:
        """A file the journal does not list (a kill between its rename and its line): whether it is seed's."""
        try:
            meta = load_episode(path).meta
        except EpisodeError:
            return False
        return meta.seed == seed and meta.source == "generated"

    # -- writing ------------------------------------------------------------------

    def record(self, seed: int, success: bool, files: Sequence[str], reason: str = "", error: str = "") -> None:
        """Append one attempt's line (after its files have landed); one write, so a kill cuts at most it.
        A failure carries its reason ("placement", "task_not_done") and, when there is one, the task's line."""
        entry: dict = {"seed": seed, "success": success, "files": [Path(f).name for f in files]}
        if not success:
            entry["reason"] = reason or "unknown"
        if error:
            entry["error"] = error
        line = json.dumps(entry) + "\n"
        try:
            with open(self.path, "a") as f:
                f.write(line)
        except OSError as exc:
            raise write_error(self.path, exc) from None


def _words(keys: list[str]) -> list[str]:
    names = {"generator_version": "generator version", "sources": "sources", "subtasks": "source subtasks",
             "seed": "--seed", "formats": "--format", "keep_failures": "--keep-failures", "variation": "--vary",
             "source_per_arm": "--source-per-arm"}
    return [names.get(k, k) for k in keys] or ["options"]


__all__ = ["Done", "JOURNAL", "Journal", "ResumeRefused", "run_identity"]
