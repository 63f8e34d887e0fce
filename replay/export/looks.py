"""Looks at export: each recorded episode rendered K times, each with its own seeded look, as K LeRobot episodes.

The unit of an export is a variant: (episode, look index). Variant j of an episode
draws its look from the look seed `looks_seed + j` and the episode's scene seed
(scenes.vary.variation: training looks seeds, apart from evaluation's held-out ones), and is
rendered from a model that differs from the recorded one only in what rendering reads
(scenes.vary.looks), so every variant has the episode's actions and states. With one
look and nothing to vary the variant is the recorded episode itself: the export is
today's, file for file.

What was varied goes into the dataset's episode metadata: a `variation` column of
meta/episodes (a JSON string per episode: the source episode, the look index and its
drawn parameters, and the physics the episode was generated with).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco

from replay.episode import Episode
from replay.export.lerobot_io import ExportError
from scenes.cameras.extra import ExtraCamera
from scenes.tasks.registry import task_for_episode
from scenes.vary.variation import GROUPS, VARIATION_KEY, Variation, VariationError, looks_kinds, task_ranges, training_look_seed
from scenes.vary.looks import apply_looks, sample_looks

COLUMN = VARIATION_KEY  # the meta/episodes column


@dataclass(frozen=True)
class Unit:
    """One exported episode: recorded episode `path` (of `steps` steps) under look `look` (None: as recorded)."""

    path: Path
    steps: int
    look: int | None = None

    @property
    def name(self) -> str:
        """The unit's name in an export's journal: the file's (a plain export's, as ever), plus the look."""
        base = str(Path(self.path).resolve())
        return base if self.look is None else f"{base}#look{self.look}"


def export_kinds(looks: int, variation: Variation | None) -> tuple[str, ...]:
    """The looks kinds an export varies: the ones asked, or with more than one look and none asked, lights,
    colors, textures and cameras."""
    kinds = looks_kinds(variation.kinds, "export") if variation is not None else ()
    return kinds or (GROUPS["looks"] if looks > 1 else ())


def varies_looks(looks: int, variation: Variation | None) -> bool:
    return looks > 1 or bool(export_kinds(looks, variation))


def check(looks: int, variation: Variation | None) -> None:
    """The flags' own checks (one line each): a whole number of looks, seeds in the training range."""
    if isinstance(looks, bool) or not isinstance(looks, int) or not 1 <= looks <= 1000:
        raise ExportError(f"looks {looks!r}: expected a whole number of looks per episode, 1 to 1000")
    if variation is not None:
        try:
            training_look_seed(variation.looks_seed, looks - 1)
        except VariationError as exc:
            raise ExportError(str(exc)) from None


def units_of(entries: list, looks: int, variation: Variation | None) -> list[Unit]:
    """The variants to export, episode by episode (`entries`: path and steps each)."""
    if not varies_looks(looks, variation):
        return [Unit(e.path, e.steps) for e in entries]
    return [Unit(e.path, e.steps, j) for e in entries for j in range(looks)]


def physics_of(ep: Episode) -> Any:
    """The physics an episode was generated with (its metadata's `variation`), or None."""
    return ep.meta.extra.get(VARIATION_KEY)


def _joints(ep: Episode) -> list[str]:
    return [j for arm in ep.meta.arms for j in arm.joints]


def variant(ep: Episode, model: mujoco.MjModel, look: int | None, looks: int, variation: Variation | None,
            cameras: tuple[ExtraCamera, ...] = ()) -> tuple[mujoco.MjModel, dict[str, Any]]:
    """(the model to render variant `look` of `ep` with, what the dataset records of it).

    `model`: the recorded model (with `cameras` added), rendered as it is when `look` is None.
    """
    record: dict[str, Any] = {"source_episode": Path(ep.path).name, "look_index": look, "looks": None,
                              "physics": physics_of(ep)}
    if look is None:
        return model, record
    variation = variation or Variation()
    kinds = export_kinds(looks, variation)
    try:
        ranges = variation.ranges(task_ranges(task_for_episode(ep.meta.scene, ep.meta.extra)))
        drawn = sample_looks(model, _joints(ep), ranges, kinds, training_look_seed(variation.looks_seed, look), ep.meta.seed)
        varied = apply_looks(ep.meta.model_xml, ep.meta.assets, drawn, ranges.texture_data, cameras)
    except VariationError as exc:
        raise ExportError(f"{Path(ep.path).name}: {exc}") from None
    record["looks"] = drawn
    return varied, record


def dataset_has_column(out: Path) -> bool:
    """Whether the LeRobot dataset at `out` has the `variation` episode column (an append must keep its columns)."""
    files = sorted((Path(out) / "meta" / "episodes").rglob("*.parquet"))
    if not files:
        return False
    import pyarrow.parquet as pq  # with LeRobot's extra

    return COLUMN in pq.read_schema(files[0]).names


def record_column(ds) -> Callable[[dict[str, Any]], None]:
    """Make `ds` write a `variation` column into its episode metadata; returns the setter of the next saved episode's.

    LeRobot's episode metadata takes extra per-episode fields through the metadata's
    save_episode; this wraps that one call on this dataset object only.
    """
    meta = ds.meta
    writer_meta = getattr(getattr(ds, "writer", None), "_meta", meta)
    original = writer_meta.save_episode
    current = {"value": "{}"}

    def save_episode(*args, **kwargs):
        if "episode_metadata" in kwargs:
            kwargs["episode_metadata"] = {**kwargs["episode_metadata"], COLUMN: current["value"]}
        else:
            args = (*args[:4], {**args[4], COLUMN: current["value"]}, *args[5:])
        return original(*args, **kwargs)

    writer_meta.save_episode = save_episode

    def set_next(value: dict[str, Any]) -> None:
        current["value"] = json.dumps(value, sort_keys=True)

    return set_next


__all__ = ["COLUMN", "Unit", "check", "dataset_has_column", "export_kinds", "physics_of", "record_column", "units_of",
           "variant", "varies_looks"]
