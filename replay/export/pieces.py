"""Exporting in finalized pieces, so that a killed export loses at most the piece in progress.

LeRobot writes a dataset's parquet and video files as episodes are saved and
only makes them readable when the dataset is finalized: killed before that,
everything written is lost (parquet files with no footer, a dataset no longer
openable). So an export here writes its episodes in pieces of a few episodes,
each a whole LeRobot export that is finalized before the next one appends to the
dataset. Appending never rewrites a finalized piece's data, episode or video
files (LeRobot moves to new files when a dataset is reopened); it does rewrite
the small metadata files (meta/info.json, meta/stats.json, meta/tasks.parquet).

A journal beside the dataset (OUT's folder, `.NAME.export/`, where LeRobot and a Hub upload
never look) records, atomically, at the start and after each piece:
- the episodes in export order and the options (a resume must ask for the same),
- how many episodes are done,
- every file of the dataset with its size,
- a copy of the small metadata files as they were.

`--resume` reads the journal, deletes every file that is not in it (the piece in
progress), puts the metadata copies back and continues with the next episode.
Because an uninterrupted export also goes piece by piece, a resumed export
writes the same files with the same frames, values, statistics and episode order.
When the export completes, the journal is removed.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from scenes.errors import TeleopError

JOURNAL = ".{name}.export"  # beside the dataset folder
MANIFEST = "manifest.json"
SNAPSHOT = "meta_snapshot"
FORMAT = 1
PIECE_EPISODES = 20  # episodes per piece: a kill loses at most this many; reopening a dataset costs ~1 s
# The options a resume must share with the export it continues (the rest only change how it runs).
SAME_OPTIONS = ("repo_id", "cameras", "image_size", "action", "task", "only_success", "video", "vcodec", "intervention",
                "object_state", "add_cameras", "variation_key", "drop_idle")
OPTION_DEFAULTS = {"add_cameras": [], "variation_key": None, "drop_idle": False}  # what a journal written before an option existed had, in effect


class ResumeError(TeleopError, ValueError):
    """An export cannot be resumed as asked, or must be (one line naming why)."""


def journal_dir(out: Path) -> Path:
    out = Path(out)
    return out.parent / JOURNAL.format(name=out.name)


def is_interrupted(out: Path) -> bool:
    """Whether `out` holds an export that stopped before it finished (it has a journal)."""
    return (journal_dir(out) / MANIFEST).is_file()


def _files(out: Path) -> dict[str, int]:
    """Every file of the dataset (journal excluded), relative path -> size in bytes."""
    found = {}
    for path in sorted(Path(out).rglob("*")):
        if path.is_file():
            found[path.relative_to(out).as_posix()] = path.stat().st_size
    return found


def _small_meta(out: Path) -> list[Path]:
    """The metadata files every append rewrites (all of meta/ but the per-episode parquet files)."""
    meta = Path(out) / "meta"
    if not meta.is_dir():
        return []
    return [p for p in sorted(meta.rglob("*")) if p.is_file() and "episodes" not in p.relative_to(meta).parts]


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _options(opts: Any) -> dict:
    out = {}
    for name in SAME_OPTIONS:
        value = getattr(opts, name, None)
        out[name] = list(value) if isinstance(value, tuple) else value
    return out


def _write_journal(out: Path, episodes: Sequence[str], opts: Any, done: int) -> None:
    """Record `done` finished episodes: snapshot the metadata, then swap in the manifest (atomic rename)."""
    journal = journal_dir(out)
    journal.mkdir(parents=True, exist_ok=True)
    snapshot_new = journal / (SNAPSHOT + ".new")
    shutil.rmtree(snapshot_new, ignore_errors=True)
    for path in _small_meta(out):
        target = snapshot_new / path.relative_to(out)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, target)
    manifest = {"format": FORMAT, "episodes": list(episodes), "options": _options(opts), "done": done,
                "files": _files(out), "snapshot": SNAPSHOT + f".{done}"}
    snapshot = journal / manifest["snapshot"]
    shutil.rmtree(snapshot, ignore_errors=True)
    if snapshot_new.exists():
        snapshot_new.rename(snapshot)
    else:
        snapshot.mkdir()
    tmp = journal / (MANIFEST + ".tmp")
    with open(tmp, "w") as f:
        json.dump(manifest, f)
        f.flush()
        os.fsync(f.fileno())
    old = _read_manifest(out)
    tmp.replace(journal / MANIFEST)
    _fsync_dir(journal)
    if old is not None and old.get("snapshot") != manifest["snapshot"]:
        shutil.rmtree(journal / old["snapshot"], ignore_errors=True)


def _read_manifest(out: Path) -> dict | None:
    path = journal_dir(out) / MANIFEST
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ResumeError(f"{path}: unreadable export journal ({exc}); remove {out} and export again") from None
    if manifest.get("format") != FORMAT:
        raise ResumeError(f"{path}: an export journal of another version; remove {out} and export again")
    return manifest


def _roll_back(out: Path, manifest: dict) -> int:
    """Delete what the journal does not list (the piece in progress), restore the metadata copies.
    Returns the number of files removed."""
    keep = manifest["files"]
    removed = 0
    for rel, size in _files(out).items():
        if rel not in keep:
            (Path(out) / rel).unlink()
            removed += 1
        elif size != keep[rel] and not any(rel == p.relative_to(out).as_posix() for p in _small_meta(out)):
            raise ResumeError(f"{out / rel}: changed since its piece was finished ({size} bytes, {keep[rel]} "
                              "recorded); remove the dataset and export again")
    for path in _small_meta(out):  # rewritten by the piece in progress: the finished pieces' versions go back
        path.unlink()
    snapshot = journal_dir(out) / manifest["snapshot"]
    for path in sorted(snapshot.rglob("*")):
        if path.is_file():
            target = Path(out) / path.relative_to(snapshot)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target)
    for path in sorted(Path(out).rglob("*"), reverse=True):  # empty folders the piece left
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()
    if Path(out).is_dir() and not any(Path(out).iterdir()):
        Path(out).rmdir()  # nothing finished yet: the first piece starts a new dataset again
    return removed


def pieces_of(episodes: Sequence[Any], size: int) -> list[list[Any]]:
    return [list(episodes[i : i + size]) for i in range(0, len(episodes), size)]


def export_in_pieces(
    episodes: Sequence[Path],
    opts: Any,
    export_piece: Callable[[list[Path], Any], Any],
    log: Callable[[str], None],
    piece_episodes: int = PIECE_EPISODES,
    names: Sequence[str] | None = None,
) -> tuple[list[Any], int]:
    """Export `episodes` (already chosen, in export order) piece by piece with `export_piece(paths, opts)`.

    opts: the export's options (an ExportOptions: `out`, `append`, `resume`, `on_episode` are read).
    names: what the journal calls each episode (default: its resolved path).
    Returns (the pieces' summaries, episodes that an earlier run had already exported).
    """
    out = Path(opts.out)
    names = list(names) if names is not None else [str(Path(p).resolve()) for p in episodes]
    done = 0
    manifest = _read_manifest(out)
    if manifest is not None and not getattr(opts, "resume", False):
        raise ResumeError(f"{out} holds an export that was interrupted ({manifest['done']} of "
                          f"{len(manifest['episodes'])} episodes done): add --resume to continue it, or remove it")
    if getattr(opts, "resume", False):
        if manifest is None:
            if out.exists():
                raise ResumeError(f"--resume: {out} holds no interrupted export (no journal {journal_dir(out).name}); "
                                  "it is complete, or was not made by teleop export")
        else:
            differ = [k for k, v in _options(opts).items() if manifest["options"].get(k, OPTION_DEFAULTS.get(k)) != v]
            if differ:  # first: other looks also name other episodes, and the option is what to fix
                raise ResumeError(f"--resume: {out} was exported with other options ({', '.join(differ)}); "
                                  "give the same ones")
            if manifest["episodes"] != names:
                raise ResumeError(f"--resume: {out} was exported from other episodes ({len(manifest['episodes'])} "
                                  f"then, {len(names)} now); give the same episode files and options")
            removed = _roll_back(out, manifest)
            done = int(manifest["done"])
            log(f"resuming {out}: {done} of {len(names)} episodes were exported; "
                f"{removed} file{'s' * (removed != 1)} of the piece in progress removed")
    if manifest is None:  # a fresh start: the dataset as it is now (none, or one appended to) is the way back
        _write_journal(out, names, opts, 0)
    summaries = []
    base_on_episode = getattr(opts, "on_episode", None)
    finished = done
    try:
        for piece in pieces_of(list(episodes)[done:], piece_episodes):

            def on_episode(n: int, frames: int, offset: int = finished - done) -> None:
                if base_on_episode is not None:
                    base_on_episode(offset + n, frames)

            has_dataset = (out / "meta" / "info.json").is_file()
            summary = export_piece(piece, replace(opts, append=has_dataset, on_episode=on_episode))
            summaries.append(summary)
            if getattr(summary, "interrupted", False):
                break
            finished += len(piece)
            _write_journal(out, names, opts, finished)
        else:
            shutil.rmtree(journal_dir(out), ignore_errors=True)
    except BaseException:
        journal = _read_manifest(out)
        if journal is not None:
            _roll_back(out, journal)  # the dataset is readable again, as its last whole piece left it
        if finished == 0 and manifest is None:  # failed before any piece was whole: as if never started
            shutil.rmtree(journal_dir(out), ignore_errors=True)
        raise  # else the journal stays: `--resume` continues from the last whole piece
    return summaries, done


__all__ = ["PIECE_EPISODES", "ResumeError", "export_in_pieces", "is_interrupted", "journal_dir", "pieces_of"]
