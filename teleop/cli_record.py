"""CLI subcommands for record (filled in by its issue)."""

import argparse


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
