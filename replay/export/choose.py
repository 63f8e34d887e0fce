"""Choosing what to export: the episode files (scanned, filtered, checked to agree), the cameras, the
LeRobot episodes to write (one per look), and the optional features and columns the dataset gets.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from replay.episode import EpisodeError, find_episodes, load_episode
from replay.export.lerobot_io import ExportError
from replay.export.looks import Unit, dataset_has_column, units_of
from replay.export.options import ExportOptions, ExportSummary, added_cameras
from replay.export.review_meta import left_out_of
from replay.features import ENV_STATE, INTERVENTION, CameraChoiceError, resolve_cameras
from scenes.vary.variation import VARIATION_KEY


@dataclass
class EpisodeEntry:
    """One scanned episode file: what must agree across an export, and what choosing it needs."""

    path: Path
    signature: tuple  # (robot, scene, control_hz): must agree across an export
    layout: tuple  # arms' joints/actuators: a same-named robot must also agree here
    success: bool
    complete: bool
    steps: int
    cameras: list[str]
    records_control: bool = False  # its steps say who drove (a policy or a person)
    varied: bool = False  # generated with physics varied (its metadata says how)
    operator: str | None = None  # who recorded it (a collection campaign's episodes)


def _scan(paths: Iterable[str | Path]) -> list[EpisodeEntry]:
    try:
        files = find_episodes(list(paths))
    except EpisodeError as exc:
        raise ExportError(str(exc)) from None
    if not files:
        raise ExportError("no episode files (.mcap, .hdf5) in " + ", ".join(map(str, paths)))
    entries = []
    for f in files:
        try:
            ep = load_episode(f)
        except EpisodeError as exc:
            raise ExportError(str(exc)) from None
        m = ep.meta
        entries.append(
            EpisodeEntry(
                path=f,
                signature=(m.robot, m.scene, m.control_hz),
                layout=tuple((a.joints, a.actuators) for a in m.arms),
                success=m.success,
                complete=m.complete and not ep.truncated,
                steps=ep.steps,
                cameras=list(m.cameras),
                records_control=m.records_control,
                varied=VARIATION_KEY in m.extra,
                operator=m.operator,
            )
        )
    return entries


def _names(paths: list[Path], limit: int = 3) -> str:
    shown = ", ".join(p.name for p in paths[:limit])
    return shown + (f" and {len(paths) - limit} more" if len(paths) > limit else "")


def _check_consistent(entries: list[EpisodeEntry]) -> None:
    groups: dict[tuple, list[Path]] = {}
    for e in entries:
        groups.setdefault((*e.signature, e.layout), []).append(e.path)
    if len(groups) > 1:
        labels = [f"robot {k[0]} / scene {k[1]} / {k[2]:g} Hz" for k in groups]
        parts = [
            f"{label}{' (other joints)' if labels.count(label) > 1 else ''}: {_names(files)}"
            for label, files in zip(labels, groups.values())
        ]
        raise ExportError("episodes come from different robots, scenes or rates; export them separately: " + "; ".join(parts))



def export_cameras(wanted: list[str] | None, have: list[str]) -> list[str]:
    """The cameras to render (replay.features.resolve_cameras), a bad choice as an ExportError."""
    try:
        return resolve_cameras(wanted, have)
    except CameraChoiceError as exc:
        raise ExportError(str(exc)) from None


def _fps(hz: float) -> int:
    fps = round(hz)
    if fps <= 0 or abs(fps - hz) > 1e-6:
        raise ExportError(f"control rate {hz:g} Hz is not a whole number of frames per second, which LeRobot needs")
    return fps


def select_episodes(paths: list, opts: ExportOptions, log: Callable[[str], None]) -> tuple[list[EpisodeEntry], ExportSummary]:
    """The episodes to export, in order, and a summary with what was skipped, the fps and the cameras."""
    entries = _scan(paths)
    summary = ExportSummary(out=opts.out)
    chosen = []
    if opts.operators is not None:
        entries = [e for e in entries if e.operator in opts.operators]
        if not entries:
            raise ExportError(f"no episodes recorded by {', '.join(opts.operators)} among the episodes given")
    for e in entries:
        if opts.only_success and not e.success:
            summary.skipped_failed += 1
        elif e.steps == 0:
            summary.skipped_empty += 1
        elif (why := left_out_of(opts.extras, e.path, opts.accepted, opts.reject_flags)) is not None:
            summary.left_out[why] = summary.left_out.get(why, 0) + 1
        else:
            chosen.append(e)
    if not chosen:
        why = f" ({summary.skipped_failed} did not succeed)" if summary.skipped_failed else ""
        if summary.left_out:
            why += " (left out by review: " + ", ".join(f"{n} {w}" for w, n in summary.left_out.items()) + ")"
        raise ExportError(f"no episodes to export among {len(entries)} found{why}")
    _check_consistent(chosen)
    cut = [e.path for e in chosen if not e.complete]
    if cut:
        log(f"note: {len(cut)} episode(s) were cut short when recorded ({_names(cut)}); exporting the steps they have")
    summary.fps = _fps(chosen[0].signature[2])
    summary.looks = opts.looks
    added = [c.name for c in added_cameras(opts)]
    clash = [name for name in added if name in chosen[0].cameras]
    if clash:
        raise ExportError(f"camera {clash[0]!r}: the recordings already have a camera of that name (they keep their own "
                          "cameras; give the added one another name)")
    summary.cameras = export_cameras(opts.cameras, chosen[0].cameras + added)
    if opts.cameras is None:  # added cameras are rendered besides the default ones
        summary.cameras += [name for name in added if name not in summary.cameras]
    return chosen, summary


def export_units(chosen: list[EpisodeEntry], opts: ExportOptions) -> list[Unit]:
    """The LeRobot episodes to write, in order: each chosen episode once per look (a shard: its plan's)."""
    if opts.variant_plan is not None:
        return [Unit(chosen[i].path, chosen[i].steps, look) for i, look in opts.variant_plan]
    return units_of(chosen, opts.looks, opts.variation)


def wants_variation_meta(opts: ExportOptions, chosen: list[EpisodeEntry]) -> bool:
    """Whether the export writes the `variation` episode column: as resolved, else when looks vary, an episode was
    generated with physics varied, or the dataset appended to has it."""
    if opts.variation_meta is not None:
        return opts.variation_meta
    if opts.looks > 1 or opts.variation is not None or any(e.varied for e in chosen):
        return True
    return bool(opts.append and opts.out.exists() and dataset_has_column(opts.out))


def _appended_features(opts: ExportOptions) -> dict | None:
    """The features of the dataset an append goes into, or None (not appending, or no dataset yet)."""
    info = opts.out / "meta" / "info.json"
    if not (opts.append and info.is_file()):
        return None
    try:
        return json.loads(info.read_text()).get("features") or {}
    except (OSError, ValueError):
        return None


def wants_object_state(opts: ExportOptions) -> bool:
    """Whether the export writes `observation.environment_state`: as asked, or as the dataset appended to has it."""
    existing = _appended_features(opts)
    return opts.object_state if existing is None else ENV_STATE in existing


def wants_intervention(opts: ExportOptions, chosen: list[EpisodeEntry]) -> bool:
    """Whether the export writes `intervention`: as asked, else when an episode records who drove
    each step, or the dataset appended to already has the feature."""
    if opts.intervention is not None:
        return opts.intervention
    if any(e.records_control for e in chosen):
        return True
    info = opts.out / "meta" / "info.json"
    if opts.append and info.is_file():
        try:
            return INTERVENTION in (json.loads(info.read_text()).get("features") or {})
        except (OSError, ValueError):
            return False
    return False

