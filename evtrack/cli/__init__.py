"""The ``evtrack`` command.

Each subcommand lives in its own module of this package and exposes
``register(subparsers) -> None``, which adds an ``argparse`` parser whose default ``func``
takes the parsed arguments and returns an exit code. Modules are discovered automatically;
``ORDER`` fixes how they are listed in ``--help``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
from collections.abc import Sequence

from evtrack.errors import EvtrackError

__all__ = ["main", "build_parser"]

ORDER = ("info", "convert", "import_data", "simulate", "flow", "train", "average_weights",
         "set_decode", "export", "track", "evaluate", "demo")


def _command_modules() -> list[str]:
    names = [m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")]
    rank = {n: i for i, n in enumerate(ORDER)}
    return sorted(names, key=lambda n: (rank.get(n, len(ORDER)), n))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evtrack",
        description=(
            "Track the 6-DoF pose of a fast-moving known object with an event camera and an "
            "RGB-D camera. Run 'evtrack COMMAND --help' for the options of each command."
        ),
    )
    from evtrack import __version__

    parser.add_argument("--version", action="version", version=f"evtrack {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _command_modules():
        module = importlib.import_module(f"{__name__}.{name}")
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``evtrack`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except EvtrackError as exc:
        print(f"evtrack {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # the reader of stdout went away (``evtrack info F | head``): not an error of the
        # command; point stdout at devnull so that the interpreter's exit flush stays quiet
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (OSError, ValueError) as exc:
        # files that cannot be read or written, values out of range: the user's to fix, so
        # one line instead of a traceback (EVTRACK_DEBUG=1 keeps the traceback)
        if os.environ.get("EVTRACK_DEBUG"):
            raise
        print(f"evtrack {args.command}: error: {_one_line(exc)} (EVTRACK_DEBUG=1 shows where)",
              file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _one_line(exc: BaseException) -> str:
    """An exception as one line: its message (with its type where the message alone would not
    say what failed, e.g. an OSError's "[Errno 21] Is a directory: 'out.csv'")."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if isinstance(exc, OSError) else text
