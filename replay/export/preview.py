"""`teleop export --preview N`: a contact sheet of the looks an export would render, before training on them.

One PNG: a row per camera, a column per look (the N variants `--looks N` would
export, with the same seeds), each the first recorded frame of the first episode.
Rendered with the export's own renderer and models, so it shows what the dataset holds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from replay.engine import replay_states
from replay.episode import EpisodeError, find_episodes, load_episode
from replay.export.choose import export_cameras
from replay.export.lerobot_io import ExportError
from replay.export.looks import check, variant
from replay.export.options import ExportOptions, added_cameras
from replay.render import FastRenderer, RenderError
from scenes.vary.textures import png_bytes

GAP = 4  # px of white between pictures


def contact_sheet(paths: list, opts: ExportOptions, count: int) -> dict:
    """Render `count` looks of the first episode's first frame for each camera into opts.out (a new .png file)."""
    out = Path(opts.out)
    if out.suffix.lower() != ".png":
        raise ExportError(f"--preview writes a PNG image: give --out FILE.png, not {out}")
    if out.exists():
        raise ExportError(f"{out} already exists (not overwriting)")
    check(count, opts.variation)
    try:
        files = find_episodes(list(paths))
        if not files:
            raise ExportError("no episode files (.mcap, .hdf5) in " + ", ".join(map(str, paths)))
        ep = load_episode(files[0])
        added = tuple(added_cameras(opts))
        recorded = ep.build_model(added)
    except EpisodeError as exc:
        raise ExportError(str(exc)) from None
    if ep.steps == 0:
        raise ExportError(f"{files[0]}: no recorded steps to show")
    cameras = export_cameras(opts.cameras, list(ep.meta.cameras) + [c.name for c in added])
    if not cameras:
        raise ExportError("no cameras to show (--cameras none)")
    columns, looks = [], []
    width, height = opts.image_size
    try:
        with FastRenderer(recorded, width, height, cameras) as renderer:
            for j in range(count):
                model, record = variant(ep, recorded, j, count, opts.variation, added)
                renderer.load(model)
                _, data = next(iter(replay_states(ep, model)))
                columns.append(np.concatenate(_spaced([renderer.render(data, c) for c in range(len(cameras))], axis=0), axis=0))
                looks.append(record["looks"])
    except RenderError as exc:
        raise ExportError(str(exc)) from None
    sheet = np.concatenate(_spaced(columns, axis=1), axis=1)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(png_bytes(sheet))
    return {"out": str(out), "episode": str(files[0]), "cameras": cameras, "looks": looks, "size": [int(sheet.shape[1]), int(sheet.shape[0])]}


def _spaced(images: list[np.ndarray], axis: int) -> list[np.ndarray]:
    """`images` with a white gap between each two, along `axis` (0: stacked, 1: side by side)."""
    out: list[np.ndarray] = []
    for i, image in enumerate(images):
        if i:
            shape = list(image.shape)
            shape[axis] = GAP
            out.append(np.full(shape, 255, dtype=np.uint8))
        out.append(image)
    return out


__all__ = ["contact_sheet"]
