"""An export of what passed review, and what review and annotation add to the dataset.

- Which episodes pass: `--accepted` keeps those with an accept verdict (replay.review.verdicts),
  `--reject-flags` leaves out those with any of the named quality flags (replay.review.quality);
  `left_out` says why each one that did not pass was left out.
- Three per-episode columns of the dataset's episode metadata, written when an export filters on
  review: `review_verdict`, `review_reviewer` and `review_flags` (the flags as a JSON list), "" when
  there is no verdict.
- Subtasks in LeRobot's own convention (its dataset_subtask docs): `meta/subtasks.parquet` maps each
  subtask (its index column, the text) to a `subtask_index`, and each frame has a `subtask_index`
  feature (int64; -1 for the frames of an episode without annotations). The subtask's text is the
  annotation's reference object (replay.subtasks.sidecar). Indices are fixed for the whole export
  before any piece or shard starts, and an append keeps the dataset's own and adds new ones after.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from replay.episode import Episode, EpisodeError, find_episodes
from replay.export.lerobot_io import ExportError
from replay.review.listing import episode_quality
from replay.review.quality import FLAGS
from replay.review.verdicts import read_verdict
from replay.subtasks.sidecar import AnnotationError, read_subtasks

REVIEW_COLUMNS = ("review_verdict", "review_reviewer", "review_flags")
SUBTASK_INDEX = "subtask_index"
SUBTASK_FEATURE = {"dtype": "int64", "shape": (1,), "names": None}
SUBTASKS_FILE = Path("meta") / "subtasks.parquet"
NOT_ACCEPTED = "not accepted"


@dataclass(frozen=True)
class Review:
    """What review says of one episode."""

    verdict: str | None
    reviewer: str
    flags: tuple[str, ...]

    def columns(self) -> dict[str, str]:
        return {"review_verdict": self.verdict or "", "review_reviewer": self.reviewer,
                "review_flags": json.dumps(list(self.flags))}


def parse_flags(text: str | Sequence[str] | None) -> tuple[str, ...]:
    """'dropped,idle' -> ('dropped', 'idle'); a name that is not a flag is an ExportError naming the flags."""
    if text is None:
        return ()
    words = [w.strip() for w in (text.split(",") if isinstance(text, str) else text) if w.strip()]
    unknown = [w for w in words if w not in FLAGS]
    if unknown:
        raise ExportError(f"--reject-flags {unknown[0]}: not a quality flag (flags: {', '.join(FLAGS)})")
    return tuple(dict.fromkeys(words))


def review_of(path: str | Path) -> Review:
    """An episode's verdict (its sidecar) and quality flags (the review cache, else scored now)."""
    found = read_verdict(path) or {}
    try:
        flags = tuple(episode_quality(path)["flags"])
    except Exception as exc:  # noqa: BLE001 - an episode that cannot be scored cannot pass a flag filter
        raise ExportError(f"{path}: cannot compute its quality flags: {str(exc).splitlines()[0]}") from None
    return Review(found.get("verdict"), found.get("reviewer") or "", flags)


def why_left_out(review: Review, accepted: bool, reject_flags: Sequence[str]) -> str | None:
    """None when the episode passes; else why not: 'not accepted', or the first rejected flag it has."""
    if accepted and review.verdict != "accept":
        return NOT_ACCEPTED
    for flag in reject_flags:
        if flag in review.flags:
            return flag
    return None


def record_review(ds) -> Callable[[Review], None]:
    """Make `ds` write the REVIEW_COLUMNS into its episode metadata; returns the setter of the next
    saved episode's (LeRobot's metadata save_episode takes extra per-episode fields; wrapped on this
    dataset object only, as replay/export/looks.py does for its column)."""
    writer_meta = getattr(getattr(ds, "writer", None), "_meta", ds.meta)
    original = writer_meta.save_episode
    current = {"value": Review(None, "", ()).columns()}

    def save_episode(*args, **kwargs):
        if "episode_metadata" in kwargs:
            kwargs["episode_metadata"] = {**kwargs["episode_metadata"], **current["value"]}
        else:
            args = (*args[:4], {**args[4], **current["value"]}, *args[5:])
        return original(*args, **kwargs)

    writer_meta.save_episode = save_episode

    def set_next(review: Review) -> None:
        current["value"] = review.columns()

    return set_next


def dataset_has_review(out: Path) -> bool:
    """Whether the LeRobot dataset at `out` has the review columns (an append must keep its columns)."""
    files = sorted((Path(out) / "meta" / "episodes").rglob("*.parquet"))
    if not files:
        return False
    import pyarrow.parquet as pq  # with LeRobot's extra

    return REVIEW_COLUMNS[0] in pq.read_schema(files[0]).names


# -- subtasks ------------------------------------------------------------------------------------------


def episode_subtasks(path: str | Path, steps: int | None = None) -> list[tuple[str, int, int]]:
    """(text, start, end) of an episode's stored subtasks; none when it has none or they do not fit."""
    try:
        found = read_subtasks(path, steps)
    except AnnotationError:
        return []
    return [(s.object, s.start, s.end) for s in found or []]


def existing_subtasks(out: Path) -> tuple[str, ...]:
    """The subtasks of the dataset at `out`, in index order (none when it has no subtasks file)."""
    file = Path(out) / SUBTASKS_FILE
    if not file.is_file():
        return ()
    import pandas as pd  # with LeRobot's extra

    frame = pd.read_parquet(file).sort_values("subtask_index")
    return tuple(str(name) for name in frame.index)


def write_subtasks_file(out: Path, names: Sequence[str]) -> Path | None:
    """meta/subtasks.parquet: the index column is the subtask's text, `subtask_index` its number."""
    if not names:
        return None
    import pandas as pd  # with LeRobot's extra

    frame = pd.DataFrame({"subtask_index": np.arange(len(names), dtype=np.int64)},
                         index=pd.Index(list(names), name="subtask"))
    file = Path(out) / SUBTASKS_FILE
    tmp = file.with_name(file.name + ".part")
    frame.to_parquet(tmp)
    tmp.replace(file)
    return file


# -- resolved once per export, for every piece and shard ------------------------------------------------


@dataclass(frozen=True)
class Extras:
    """What an export adds of one episode besides its recording: its review (None when the export does
    not filter on review) and its subtasks as (text, start, end)."""

    review: Review | None
    subtasks: tuple[tuple[str, int, int], ...] = ()


def episode_key(path: str | Path) -> str:
    """An episode's key in `Extras` maps: its file name and size (a Ray shard gets the file's bytes under
    another folder, and no sidecars)."""
    return f"{Path(path).name}:{os.path.getsize(path)}"


def resolve_extras(paths: Sequence[str | Path], accepted: bool, reject_flags: Sequence[str], out: Path,
                   append: bool) -> tuple[dict[str, Extras], tuple[str, ...]]:
    """Per episode (episode_key) its Extras, and the export's subtask texts in index order.

    Reviews are looked up only when the export filters on review; flags are computed only for the
    episodes an accept filter keeps. Appending to a dataset without `subtask_index` adds none.
    """
    try:
        files = find_episodes(list(paths))
    except EpisodeError as exc:
        raise ExportError(str(exc)) from None
    filtering = accepted or bool(reject_flags)
    extras: dict[str, Extras] = {}
    names: dict[str, None] = dict.fromkeys(existing_subtasks(out) if append else ())
    for path in files:
        review = None
        if filtering:
            found = read_verdict(path) or {}
            if accepted and found.get("verdict") != "accept":
                review = Review(found.get("verdict"), found.get("reviewer") or "", ())
            else:
                review = review_of(path)
        spans = tuple(episode_subtasks(path))
        for text, _, _ in spans:
            names.setdefault(text)
        extras[episode_key(path)] = Extras(review, spans)
    if append and (out / "meta" / "info.json").is_file():
        try:
            features = json.loads((out / "meta" / "info.json").read_text()).get("features") or {}
        except (OSError, ValueError):
            features = {}
        if SUBTASK_INDEX not in features:
            names = {}
    return extras, tuple(names)


def left_out_of(extras: dict[str, Extras] | None, path: Path, accepted: bool, reject_flags: Sequence[str]) -> str | None:
    """Why review leaves the episode at `path` out (None: it passes, or the export does not filter on review)."""
    if not (accepted or reject_flags) or extras is None:
        return None
    found = extras.get(episode_key(path))
    if found is None or found.review is None:
        return NOT_ACCEPTED if accepted else None
    return why_left_out(found.review, accepted, reject_flags)


def review_for(extras: dict[str, Extras] | None, path: Path) -> Review:
    """The review to write into the episode metadata ("" columns when there is none)."""
    found = (extras or {}).get(episode_key(path))
    return found.review if found is not None and found.review is not None else Review(None, "", ())


def subtask_ids_for(extras: dict[str, Extras] | None, names: Sequence[str], episode: Episode) -> np.ndarray:
    """(steps,) int64 subtask indices of an episode from its resolved spans; -1 where it has none
    (or spans made for another length)."""
    ids = np.full(episode.steps, -1, dtype=np.int64)
    found = (extras or {}).get(episode_key(episode.path))
    if found is None or not found.subtasks or found.subtasks[-1][2] != episode.steps:
        return ids
    index = {name: i for i, name in enumerate(names)}
    for text, start, end in found.subtasks:
        ids[start:end] = index[text]
    return ids
