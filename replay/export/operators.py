"""Who recorded each episode, in the dataset: the `operator` column, and `--operator` to export only theirs.

Episodes of a collection campaign (issue 35) carry `operator` in their metadata. An export
that has any such episode writes an `operator` column into the dataset's episode metadata
(meta/episodes: one string per episode, "" for an episode that names no operator); an
append keeps the dataset's columns, so it writes the column exactly when the dataset has it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from replay.export.lerobot_io import ExportError

OPERATOR_COLUMN = "operator"


def parse_operators(text: str | Sequence[str] | None) -> tuple[str, ...] | None:
    """'ana,bo' -> ('ana', 'bo'); None when no filter is asked for; an empty list is an ExportError."""
    if text is None:
        return None
    words = [w.strip() for w in (text.split(",") if isinstance(text, str) else text) if w.strip()]
    if not words:
        raise ExportError("--operator: give one or more operator names, comma separated")
    return tuple(dict.fromkeys(words))


def dataset_has_operator(out: Path) -> bool:
    """Whether the LeRobot dataset at `out` has the `operator` episode column."""
    files = sorted((Path(out) / "meta" / "episodes").rglob("*.parquet"))
    if not files:
        return False
    import pyarrow.parquet as pq  # with LeRobot's extra

    return OPERATOR_COLUMN in pq.read_schema(files[0]).names


def wants_operator_column(operators: Sequence[str | None], out: Path, append: bool) -> bool:
    """Written when an episode names its operator; when appending, exactly when the dataset has the column."""
    if append and (Path(out) / "meta" / "info.json").is_file():
        return dataset_has_operator(out)
    return any(operators)


def record_operator(ds) -> Callable[[str | None], None]:
    """Make `ds` write the `operator` column into its episode metadata; returns the setter of the next
    saved episode's (LeRobot's metadata save_episode takes extra per-episode fields; wrapped on this
    dataset object only, as replay/export/looks.py does for its column)."""
    writer_meta = getattr(getattr(ds, "writer", None), "_meta", ds.meta)
    original = writer_meta.save_episode
    current = {"value": ""}

    def save_episode(*args, **kwargs):
        if "episode_metadata" in kwargs:
            kwargs["episode_metadata"] = {**kwargs["episode_metadata"], OPERATOR_COLUMN: current["value"]}
        else:
            args = (*args[:4], {**args[4], OPERATOR_COLUMN: current["value"]}, *args[5:])
        return original(*args, **kwargs)

    writer_meta.save_episode = save_episode

    def set_next(operator: str | None) -> None:
        current["value"] = operator or ""

    return set_next
