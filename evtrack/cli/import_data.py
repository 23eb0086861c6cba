"""``evtrack import DATASET ...``: a recording of one of the field's datasets as sequences."""

from __future__ import annotations

import argparse

__all__ = ["register"]

DESCRIPTION = """\
Read a recording in one of the field's dataset layouts and write evtrack sequence folders
(meta.yaml, events.h5, rgb/, depth/, groundtruth.h5), which every other command takes. Each
dataset has its own subcommand; 'evtrack import DATASET --help' gives its options.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from evtrack.datasets import importer_modules

    p = subparsers.add_parser(
        "import", help="import a dataset's recording (YCB-Ev, BOP, ECD) as sequence folders",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="dataset", metavar="DATASET")
    for module in importer_modules():
        module.register_import(sub)
    p.set_defaults(func=lambda args: _usage(p))


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 2
