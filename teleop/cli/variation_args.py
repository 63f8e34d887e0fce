"""The variation flags every command shares: `--vary`, `--vary-range`, `--texture`, `--looks-seed` (scenes/vary/variation.py).

A bad word, range or file is a VariationError: one line and exit 2, before anything runs.
"""

from __future__ import annotations

import argparse

from scenes.vary.variation import HELD_OUT_BASE, KEYS, Variation, VariationError, parse_range_flags, parse_vary, read_texture

PHYSICS_WORDS = "physics (= size,mass,friction,damping), size, mass, friction, damping, distractors (physical)"
LOOKS_WORDS = "looks (= lights,colors,textures,cameras), lights, colors, textures, cameras, distractors (visual only)"
EVAL_WORDS = ("physics (= size,mass,friction,damping), looks (= lights,colors,textures,cameras), size, mass, friction, damping, "
              "lights, colors, textures, cameras, distractors (physical)")


def add_range_args(p: argparse.ArgumentParser, textures: bool) -> None:
    p.add_argument("--vary-range", action="append", default=[], metavar="KEY=LO,HI",
                   help="override one range of the task's [variation] table (repeatable), e.g. mass=0.5,2 or lights=1,4; "
                   f"keys: {', '.join(k for k in KEYS if k != 'texture_files')}")
    if textures:
        p.add_argument("--texture", action="append", default=[], metavar="FILE.png",
                       help="an image to texture the table and floor with, among the procedural ones (repeatable)")


def add_physics_args(p: argparse.ArgumentParser) -> None:
    """`teleop run|serve|generate`: physics drawn per seed into the episode's model."""
    p.add_argument("--vary", default=None, metavar="WORDS",
                   help=f"vary the physics of each seed's scene (recorded in the episode): comma list of {PHYSICS_WORDS}")
    add_range_args(p, textures=False)


def add_looks_seed_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--looks-seed", default="0", metavar="S", help=what)


def _looks_seed(text: str) -> int:
    try:
        value = int(text)
    except (TypeError, ValueError):
        value = -1
    if not 0 <= value < HELD_OUT_BASE:
        raise VariationError(f"--looks-seed {text!r}: expected a whole number 0..{HELD_OUT_BASE - 1}")
    return value


def variation_from(args: argparse.Namespace, stage: str, split: str = "train") -> Variation | None:
    """The Variation the flags ask for, checked now; None when they ask for none."""
    kinds = parse_vary(getattr(args, "vary", None), stage)
    overrides = parse_range_flags(getattr(args, "vary_range", None) or [])
    textures = tuple(read_texture(path, "--texture") for path in getattr(args, "texture", None) or [])
    seed = _looks_seed(getattr(args, "looks_seed", "0"))
    if not kinds and not overrides and not textures and seed == 0 and split == "train":
        return None
    return Variation(kinds=kinds, overrides=overrides, texture_files=textures, split=split, looks_seed=seed)


__all__ = ["EVAL_WORDS", "LOOKS_WORDS", "PHYSICS_WORDS", "add_looks_seed_arg", "add_physics_args", "add_range_args", "variation_from"]
