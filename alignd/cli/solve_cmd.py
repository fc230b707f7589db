"""alignctl subcommands (filled in by its issue)."""

import argparse


def register(sub: argparse._SubParsersAction) -> None:  # noqa: ARG001
    """Add this module's subcommands."""
