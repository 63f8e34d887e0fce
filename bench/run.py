"""`teleop bench`: run every speed measurement and print the figures.

Each bench module exposes `measure(quick: bool) -> dict[str, float]`; the keys
are the figures issues name (medians or ratios, never pass/fail).
"""

from __future__ import annotations

import importlib

MODULES = ("control", "recording", "web", "export", "devices")


def run_all(quick: bool = False, only: list[str] | None = None, progress: bool = True) -> dict[str, float]:
    """Run the named bench modules (all by default) and merge their figures."""
    from rich.console import Console

    console = Console(stderr=True)
    results: dict[str, float] = {}
    for name in only or MODULES:
        if name not in MODULES:
            raise ValueError(f"unknown bench {name!r} (benches: {', '.join(MODULES)})")
        module = importlib.import_module(f"bench.{name}")
        if progress:
            console.print(f"[dim]bench {name}...[/dim]")
        results.update(module.measure(quick))
    return results
