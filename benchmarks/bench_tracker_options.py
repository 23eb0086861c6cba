"""The tracker's speed with config options against its defaults, side by side.

    python benchmarks/bench_tracker_options.py --sequence DIR [DIR ...]
        --option NAME=YAML [--option NAME=YAML ...] [--repeats 2] [--frames memory]
        [--method full] [--threads 2]

Each ``--option`` names a set of :class:`~evtrack.tracking.config.TrackerConfig` overrides,
written as a YAML mapping (parsed with ``yaml.safe_load``, checked by ``TrackerConfig`` before
anything runs), e.g.::

    --option g20='flow_batch_steps: 20'
    --option pw48='{load: {search_per_roi_window: 48, max_searched_per_step: 1875}}'

``defaults`` (no override) always runs first, as the reference. ``method`` and
``torch_threads`` are this script's ``--method`` and ``--threads``, the same for every
setting, so an option may not set them. Each run is a fresh child
process, the settings interleaved run by run so that the machine's load drifts over all of
them alike; each child tracks the sequence twice and times the second run (the first loads
the compiled kernels). Oracle poses (1 cm / 0.03 rad noise), as in
``benchmarks/bench_tracker.py``; ``--frames memory`` decodes the RGB-D frames beforehand (as
a live camera gives them), ``files`` while tracking. Printed per sequence and setting: the
median processing time, the real-time factor (processing / sequence time), the flow stage's
time and every run's time. Timings on a shared machine drift by 10 % within an hour: compare
settings only within one invocation, and use ``--repeats``. The options' errors are not
measured here: ``evtrack evaluate --config`` gives them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml
from tracker_runs import add_run_arguments, check_run_arguments, compare, run_child, time_tracking

REFERENCE = "defaults"
FIXED = {"method": "--method", "torch_threads": "--threads"}
"""Config fields every setting shares, set by the script's own arguments."""


def parse_option(text: str) -> tuple[str, dict]:
    """``NAME=YAML`` -> ``(NAME, overrides)``; the overrides are checked by ``TrackerConfig``.

    Raises:
        argparse.ArgumentTypeError: no ``=``, an empty or reserved name, YAML that does not
            parse to a mapping, or fields the tracker config does not accept.
    """
    from evtrack.errors import ConfigError
    from evtrack.tracking.config import TrackerConfig

    name, sep, body = text.partition("=")
    name = name.strip()
    if not sep or not name or name == REFERENCE:
        raise argparse.ArgumentTypeError(
            f"{text!r}: write NAME=YAML, e.g. g20='flow_batch_steps: 20' (NAME not "
            f"{REFERENCE!r})")
    try:
        overrides = yaml.safe_load(body)
    except yaml.YAMLError as exc:
        problem = " ".join(str(exc).split())
        raise argparse.ArgumentTypeError(f"{name}: not YAML ({problem})") from None
    if not isinstance(overrides, dict) or not overrides:
        raise argparse.ArgumentTypeError(
            f"{name}: the overrides must be a non-empty YAML mapping, got {body!r}")
    fixed = sorted(set(overrides) & set(FIXED))
    if fixed:
        raise argparse.ArgumentTypeError(
            f"{name}: {', '.join(fixed)} is set for every setting by "
            f"{', '.join(FIXED[f] for f in fixed)}, not by an option")
    try:
        TrackerConfig.from_dict(overrides)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(f"{name}: {exc}") from None
    return name, overrides


def _spawn(sequence: Path, overrides: dict, name: str, args: argparse.Namespace) -> dict:
    cmd = [sys.executable, __file__, "--child", "--sequence", str(sequence), "--method",
           args.method, "--threads", str(args.threads), "--frames", args.frames,
           "--overrides", json.dumps(overrides)]
    return run_child(cmd, f"{sequence}, {name}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--option", type=parse_option, action="append", default=[],
                    metavar="NAME=YAML", help="a named set of tracker config overrides "
                                              "(repeatable)")
    ap.add_argument("--frames", choices=("files", "memory"), default="memory",
                    help="RGB-D frames decoded while tracking (files) or beforehand (memory, "
                         "the default)")
    ap.add_argument("--overrides", help=argparse.SUPPRESS)
    add_run_arguments(ap, "setting")
    args = ap.parse_args(argv)
    if args.child:
        config = {"method": args.method, **json.loads(args.overrides or "{}")}
        print(json.dumps(time_tracking(args.sequence[0], config, args.threads, args.frames)))
        return 0
    if not args.option:
        ap.error("give at least one --option NAME=YAML to compare with the defaults")
    check_run_arguments(ap, args)
    missing = [str(s) for s in args.sequence if not (s / "meta.yaml").is_file()]
    if missing:
        ap.error(f"not sequence folders (no meta.yaml): {', '.join(missing)}")
    settings = {REFERENCE: {}}
    for name, overrides in args.option:
        if name in settings:
            ap.error(f"--option {name} is given twice")
        settings[name] = overrides
    print(f"evtrack.Tracker ({args.method}, {args.threads} threads, oracle poses, frames "
          f"{'decoded beforehand' if args.frames == 'memory' else 'read while tracking'}); "
          f"median of {args.repeats} interleaved runs, each a fresh process")
    for name, overrides in settings.items():
        print(f"  {name}: {json.dumps(overrides) if overrides else 'the tracker as it ships'}")
    compare(args.sequence, list(settings), "setting", args.repeats,
            lambda seq, name: _spawn(seq, settings[name], name, args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
