"""The shape every ``evtrack`` command's parser shares; a helper, not a command (the modules
of this package whose names start with ``_`` are not commands)."""

from __future__ import annotations

import argparse
import textwrap

__all__ = ["command_parser"]


def command_parser(subparsers: argparse._SubParsersAction, name: str, summary: str,
                   description: str, epilog: str) -> argparse.ArgumentParser:
    """The sub-command ``name``: ``summary`` in ``evtrack --help``, ``description`` (a paragraph,
    wrapped to 88 columns) and ``epilog`` (examples, kept as written) in its own ``--help``."""
    return subparsers.add_parser(name, help=summary, description=textwrap.fill(description, 88),
                                 epilog=epilog,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
