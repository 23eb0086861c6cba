"""``evtrack convert IN OUT``: convert an event file between formats, streaming."""

from __future__ import annotations

import argparse
import math
import sys
import textwrap
from pathlib import Path

__all__ = ["register", "run", "convert"]

DEFAULT_WINDOW_MS = 100.0
US_PER_MS = 1000
_WIDTH = 79  # help text width


def _description() -> str:
    from evtrack.io.formats import formats_help

    intro = (
        "Convert an event file from any readable format to any writable one. The input is read "
        "window by window (--window-ms), validated (time order, coordinates inside the sensor, "
        "polarity) and appended to the output, so files larger than memory are fine (except "
        ".npz input, which is loaded whole). The output appears only when the conversion "
        "succeeded (written to a temporary file, then renamed)."
    )
    text = (
        "Text files hold one event per line, 't x y p' with t in seconds and p 1 (ON) / 0 (OFF). "
        "A text file without a '# sensor_size W H' header has no sensor size: pass "
        "--sensor-size W H when converting it to HDF5."
    )
    return (
        f"{textwrap.fill(intro, _WIDTH)}\n\n"
        "Formats (input by content and extension; output by extension or --to):\n"
        f"{formats_help()}\n\n{textwrap.fill(text, _WIDTH)}"
    )


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "convert",
        help="convert an event file between formats (hdf5, text, npz; reads aedat4, raw too)",
        description=_description(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("input", type=Path, help="event file to read")
    parser.add_argument("output", type=Path, help="event file to write (.h5, .txt or .npz)")
    parser.add_argument("--to", choices=("hdf5", "text", "npz"), default=None,
                        help="output format (default: from the output's extension)")
    parser.add_argument("--window-ms", type=float, default=DEFAULT_WINDOW_MS,
                        help=f"streaming window in ms (default: {DEFAULT_WINDOW_MS:g})")
    parser.add_argument("--sensor-size", type=int, nargs=2, metavar=("W", "H"), default=None,
                        help="sensor width and height in pixels (overrides the input's)")
    parser.add_argument("--compression", choices=("none", "lzf", "gzip"), default="none",
                        help="HDF5 output compression (default: none, fastest to read)")
    parser.add_argument("--compress", action="store_true", help="deflate .npz output")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace OUTPUT if it exists (default: refuse)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def convert(
    src: str | Path,
    dst: str | Path,
    *,
    window_us: int = int(DEFAULT_WINDOW_MS * US_PER_MS),
    to: str | None = None,
    sensor_size: tuple[int, int] | None = None,
    progress: bool = False,
    **writer_options: object,
) -> int:
    """Convert ``src`` to ``dst`` window by window; returns the number of events written.

    Args:
        src: input event file (any readable format).
        dst: output event file; written atomically.
        window_us: streaming window in µs.
        to: output format, default from ``dst``'s extension.
        sensor_size: overrides the input's sensor size.
        progress: show a tqdm bar on stderr (disabled automatically when not a TTY).
        **writer_options: passed to :func:`evtrack.io.open_writer`.
    """
    from tqdm import tqdm

    from evtrack.io import open_events, open_writer

    written = 0
    with open_events(src, sensor_size=sensor_size) as reader:
        total = reader.num_events if reader.indexed else None
        bar = tqdm(total=total, unit="ev", unit_scale=True, file=sys.stderr,
                   disable=None if progress else True, desc=Path(src).name)
        try:
            with open_writer(dst, reader.sensor_size, format=to, **writer_options) as writer:
                for window in reader.iter_windows(window_us):
                    writer.write(window)
                    written += len(window)
                    bar.update(len(window))
        finally:
            bar.close()
    return written


def run(args: argparse.Namespace) -> int:
    from evtrack.errors import EvtrackError
    from evtrack.io.api import _writable_format
    from evtrack.io.formats import format_from_extension

    if not (math.isfinite(args.window_ms) and args.window_ms > 0):
        raise EvtrackError(f"--window-ms must be a positive number, got {args.window_ms}")
    if args.output.exists() and not args.overwrite:
        raise EvtrackError(f"{args.output} exists; pass --overwrite to replace it")
    if args.input.resolve() == args.output.resolve():
        raise EvtrackError("input and output are the same file")
    try:
        fmt = _writable_format(args.output, args.to)
    except EvtrackError as exc:  # the library's hint names its argument; the command's is --to
        raise EvtrackError(str(exc).replace("or pass format=...", "or give --to")) from exc
    named = format_from_extension(args.output)
    if args.to and named and named != fmt:
        print(f"warning: writing {fmt} to {args.output}, whose extension says {named}",
              file=sys.stderr)
    options: dict[str, object] = {}
    if fmt == "hdf5" and args.compression != "none":
        options["compression"] = args.compression
    if fmt == "npz" and args.compress:
        options["compress"] = True
    try:
        n = convert(
            args.input, args.output, window_us=max(1, round(args.window_ms * US_PER_MS)),
            to=fmt, sensor_size=tuple(args.sensor_size) if args.sensor_size else None,
            progress=not args.quiet, **options,
        )
    except EvtrackError as exc:  # the library's hint names its argument; the command's is this
        text = str(exc).replace("give sensor_size=(width, height)", "give --sensor-size W H")
        if text == str(exc):
            raise
        raise EvtrackError(f"{args.input}: {text}") from exc
    print(f"wrote {n} events to {args.output} ({fmt})")
    return 0
