"""Read throughput of evtrack's event readers next to the decoder library each one wraps.

Run: ``python benchmarks/bench_io.py [--events 4000000] [--repeat 3] [--evt3-copies 20]``

Every row times a whole-file read into memory, best of ``--repeat`` runs, in this one process:

* HDF5 (synthetic, uncompressed / lzf / gzip): ``evtrack.io.read_events`` (validated Events)
  against plain ``h5py`` reads of the four datasets (``ds[()]``).
* text (synthetic, ``t x y p`` with 6 decimals): evtrack's chunked exact parser against
  ``numpy.loadtxt`` (float64) and ``numpy.fromstring(sep=' ')`` (float64, the fastest plain
  numpy parse of the whole text we found); neither of those gives exact µs.
* EVT3 (the real sample, and a larger file made of ``--evt3-copies`` copies of its data
  section; the decoder reads the repeated 24-bit time as wrap-arounds, so the copies follow
  each other in time — the reader's validation confirms the result is sorted): evtrack against
  ``expelliarmus.Wizard.read``.
* AEDAT4 (the real sample): evtrack against iterating ``aedat.Decoder`` and concatenating the
  event packets.

Streaming rows (``iter_events`` in 10 ms windows) are listed against the same references.
The machine is shared: expect noise of tens of percent between runs.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import aedat
import h5py
import numpy as np
from expelliarmus import Wizard

from evtrack.events import Events
from evtrack.io import iter_events, read_events, write_events
from evtrack.io.formats import parse_raw_header

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "formats"
EVT3_SAMPLE = SHARED / "expelliarmus_prophesee_raw" / "evt3_sample.raw"
AEDAT4_SAMPLE = SHARED / "tonic_dvxplorer_aedat4" / "sample.aedat4"
SENSOR = (640, 480)
MEAN_RATE_EV_PER_S = 2_000_000  # synthetic event rate (sets the timestamps' spacing)
STREAM_WINDOW_US = 10_000


def synthetic(n: int, seed: int = 0) -> Events:
    rng = np.random.default_rng(seed)
    dt = 1_000_000 / MEAN_RATE_EV_PER_S
    t = np.cumsum(rng.poisson(dt, n)).astype(np.int64) + 1_000_000
    return Events(rng.integers(0, SENSOR[0], n).astype(np.int16),
                  rng.integers(0, SENSOR[1], n).astype(np.int16), t,
                  rng.choice(np.array([-1, 1], np.int8), n), SENSOR)


def best_time(fn: Callable[[], int], repeat: int) -> tuple[float, int]:
    """Best wall time of ``repeat`` calls and the event count the call returned."""
    best, count = float("inf"), 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        count = fn()
        best = min(best, time.perf_counter() - t0)
    return best, count


# ----------------------------------------------------------------------------- references
def h5py_raw(path: Path) -> int:
    with h5py.File(path, "r") as f:
        arrays = [f[f"events/{k}"][()] for k in ("x", "y", "t", "p")]
    return len(arrays[2])


def loadtxt_ref(path: Path) -> int:
    a = np.loadtxt(path)
    np.rint(a[:, 0] * 1e6).astype(np.int64)
    return a.shape[0]


def fromstring_ref(path: Path) -> int:
    text = path.read_text()
    start = text.index("\n", text.index("# sensor_size")) + 1  # skip the comment header
    end = text.rindex("# num_events")
    a = np.fromstring(text[start:end], dtype=np.float64, sep=" ").reshape(-1, 4)
    np.rint(a[:, 0] * 1e6).astype(np.int64)
    return a.shape[0]


def expelliarmus_ref(path: Path) -> int:
    return len(Wizard(encoding="evt3").read(path))


def aedat_ref(path: Path) -> int:
    packets = [p["events"] for p in aedat.Decoder(str(path)) if "events" in p]
    return len(np.concatenate(packets))


def evtrack_read(path: Path) -> int:
    return len(read_events(path))


def evtrack_stream(path: Path) -> int:
    return sum(len(w) for w in iter_events(path, window_us=STREAM_WINDOW_US))


def repeated_evt3(dst: Path, copies: int) -> Path:
    data = EVT3_SAMPLE.read_bytes()
    header = parse_raw_header(data[:4096])
    dst.write_bytes(data[: header.length] + data[header.length :] * copies)
    return dst


# ----------------------------------------------------------------------------- main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, default=4_000_000, help="synthetic file size")
    parser.add_argument("--repeat", type=int, default=3, help="runs per row (best is kept)")
    parser.add_argument("--evt3-copies", type=int, default=20,
                        help="copies of the EVT3 sample's data in the large EVT3 file")
    args = parser.parse_args()

    rows: list[tuple[str, Path, Callable[[Path], int], str, Callable[[Path], int]]] = []
    with tempfile.TemporaryDirectory(prefix="bench_io-") as tmp:
        tmp = Path(tmp)
        ev = synthetic(args.events)
        for comp in (None, "lzf", "gzip"):
            path = tmp / f"synthetic_{comp or 'none'}.h5"
            write_events(path, ev, compression=comp)
            rows.append((f"hdf5 ({comp or 'uncompressed'})", path, evtrack_read,
                         "h5py ds[()] x4", h5py_raw))
        rows.append(("hdf5 iter 10 ms", tmp / "synthetic_none.h5", evtrack_stream,
                     "h5py ds[()] x4", h5py_raw))
        text = tmp / "synthetic.txt"
        write_events(text, ev)
        rows.append(("text", text, evtrack_read, "np.fromstring f64", fromstring_ref))
        rows.append(("text", text, evtrack_read, "np.loadtxt f64", loadtxt_ref))
        rows.append(("text iter 10 ms", text, evtrack_stream, "np.fromstring f64",
                     fromstring_ref))
        if EVT3_SAMPLE.is_file():
            big = repeated_evt3(tmp / f"evt3_x{args.evt3_copies}.raw", args.evt3_copies)
            rows.append(("evt3 (sample)", EVT3_SAMPLE, evtrack_read, "Wizard.read",
                         expelliarmus_ref))
            rows.append((f"evt3 ({args.evt3_copies} copies)", big, evtrack_read, "Wizard.read",
                         expelliarmus_ref))
            rows.append((f"evt3 ({args.evt3_copies} copies) iter 10 ms", big, evtrack_stream,
                         "Wizard.read", expelliarmus_ref))
        else:
            print(f"(EVT3 rows skipped: {EVT3_SAMPLE} not found)")
        if AEDAT4_SAMPLE.is_file():
            rows.append(("aedat4 (sample)", AEDAT4_SAMPLE, evtrack_read, "aedat.Decoder",
                         aedat_ref))

        header = (f"{'reader':30s} {'events':>10s} {'MB':>7s} {'evtrack Mev/s':>14s} "
                  f"{'reference':>18s} {'ref Mev/s':>10s} {'ratio':>6s}")
        print(header)
        print("-" * len(header))
        for name, path, ours, ref_name, ref in rows:
            t_ours, n_ours = best_time(lambda p=path, f=ours: f(p), args.repeat)
            t_ref, n_ref = best_time(lambda p=path, f=ref: f(p), args.repeat)
            assert n_ours == n_ref, (name, n_ours, n_ref)
            mb = path.stat().st_size / 1e6
            r_ours, r_ref = n_ours / t_ours / 1e6, n_ref / t_ref / 1e6
            print(f"{name:30s} {n_ours:10d} {mb:7.1f} {r_ours:14.1f} {ref_name:>18s} "
                  f"{r_ref:10.1f} {r_ours / r_ref:6.2f}")
        print("ratio = evtrack throughput / reference throughput (higher is better for evtrack)")


if __name__ == "__main__":
    main()
