"""Textures made in code (checker, noise, grain) and the PNG bytes they and contact sheets are stored as.

Procedural textures are pure functions of a seed: a look records only (kind, seed,
colours) and any process makes the identical pixels again, so a dataset's episode
metadata is enough to redo its pictures. Images are uint8 (H, W, 3), top row first.
PNG is written with zlib alone (no imaging library is a dependency).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence

import numpy as np

PROCEDURAL = ("checker", "noise", "grain")
TEXTURE_SIZE = 128  # px a side: tiled over a table or a cube, more shows no more at 224 px images
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _mix(a: Sequence[float], b: Sequence[float], t: np.ndarray) -> np.ndarray:
    """Blend colour a (t = 0) to colour b (t = 1), rgb in 0..1 -> uint8 (H, W, 3)."""
    a3, b3 = np.asarray(a, float)[:3], np.asarray(b, float)[:3]
    out = a3 + (b3 - a3) * t[..., None]
    return np.clip(np.round(out * 255.0), 0, 255).astype(np.uint8)


def _smooth_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Value noise in 0..1: a random `cells` x `cells` lattice, bilinearly upsampled, tiling seamlessly."""
    grid = rng.random((cells, cells))
    x = np.arange(size) * cells / size
    i0 = np.floor(x).astype(int)
    f = x - i0
    f = f * f * (3 - 2 * f)  # smoothstep: no creases along the lattice lines
    i1 = (i0 + 1) % cells
    rows = grid[i0][:, i0] * (1 - f)[None, :] + grid[i0][:, i1] * f[None, :]
    rows1 = grid[i1][:, i0] * (1 - f)[None, :] + grid[i1][:, i1] * f[None, :]
    return rows * (1 - f)[:, None] + rows1 * f[:, None]


def procedural(kind: str, seed: int, rgb1: Sequence[float], rgb2: Sequence[float], size: int = TEXTURE_SIZE) -> np.ndarray:
    """A (size, size, 3) uint8 texture of `kind` between two colours (rgb, 0..1); the same arguments, the same pixels.

    checker: squares of 2-8 a side; noise: smooth blotches at two scales; grain: wood-like
    bands bent by noise. Every kind tiles (its left edge meets its right edge).
    """
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, PROCEDURAL.index(kind) if kind in PROCEDURAL else 99])
    if kind == "checker":
        n = int(rng.choice([2, 4, 8]))
        ij = np.arange(size) * n // size
        t = ((ij[:, None] + ij[None, :]) % 2).astype(float)
    elif kind == "noise":
        t = 0.65 * _smooth_noise(rng, size, 4) + 0.35 * _smooth_noise(rng, size, 16)
        t = (t - t.min()) / max(float(t.max() - t.min()), 1e-9)
    elif kind == "grain":
        bands = int(rng.integers(3, 9))
        bend = _smooth_noise(rng, size, 4)
        y = np.arange(size)[:, None] / size
        t = 0.5 + 0.5 * np.sin(2 * np.pi * (bands * y + 1.5 * bend))
        t = t ** 3 + 0.15 * _smooth_noise(rng, size, 32)
        t = np.clip(t, 0.0, 1.0)
    else:
        raise ValueError(f"unknown procedural texture {kind!r} (kinds: {', '.join(PROCEDURAL)})")
    return _mix(rgb1, rgb2, t)


def png_bytes(image: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 image as PNG file bytes (8-bit RGB, no filter)."""
    image = np.ascontiguousarray(image, dtype=np.uint8)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {image.shape}")
    h, w, _ = image.shape
    raw = b"".join(b"\x00" + image[r].tobytes() for r in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return PNG_MAGIC + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")


def is_png(data: bytes) -> bool:
    return data[:8] == PNG_MAGIC


__all__ = ["PROCEDURAL", "TEXTURE_SIZE", "is_png", "png_bytes", "procedural"]
