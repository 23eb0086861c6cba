"""Configuration of the triplet-matching optical flow (:class:`FlowConfig`).

Every parameter has a documented default; :meth:`FlowConfig.from_dict` and
:meth:`FlowConfig.from_yaml` load a (partial) mapping and reject unknown or ill-typed fields
with a :class:`~evtrack.errors.ConfigError` that names the field.

The exact matching rule the parameters feed (stated once here, implemented in
:mod:`evtrack.flow.candidates` and re-implemented independently in the tests):

Burst filter first: with ``refractory_us > 0`` an event is skipped (neither matched nor
stored in the history) when the previous event of the same pixel (kept or not, either
polarity) has the same polarity and ``t - t_prev <= refractory_us``. Then, for an event ``e_k`` with
polarity ``p_k`` and every displacement ``d`` of the search set
(all integer offsets with Chebyshev norm ``1..radius``, see :func:`search_offsets`), let
``H_j`` be the last ``history`` events of polarity ``p_k`` at pixel ``x_k - d`` and ``H_i``
those at ``x_k - 2d``, as seen just before ``e_k`` (events earlier in the stream, including
earlier events with the same timestamp). Every pair ``e_j in H_j``, ``e_i in H_i`` with

* ``t_k - t_j >= 1`` and ``t_j - t_i >= 1`` (µs; time strictly increases along the triplet),
* ``|(t_k - t_j) - (t_j - t_i)| * 1000 <= tolerance_us * 1000 + tolerance_permille * (t_k - t_i)``
  (constant velocity within an absolute plus a relative tolerance; integer arithmetic),
* ``min_speed <= |x_k - x_i| / (t_k - t_i) <= max_speed`` (px/s; applied as integer bounds
  on ``t_k - t_i`` that reproduce this float64 test exactly, see :func:`dt_bounds_us`),
* ``t_k - t_i <= max_span_us`` when ``max_span_us > 0`` (µs)

gives the candidate flow ``(x_k - x_i) / (t_k - t_i) = 2 d / (t_k - t_i)`` in px/s.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evtrack import configs
from evtrack.configs import Config
from evtrack.errors import ConfigError
from evtrack.flow.constants import MAX_DT_US, US_PER_S

__all__ = ["FlowConfig", "search_offsets", "dt_bounds_us", "BACKENDS", "LOOKUPS"]

BACKENDS = ("auto", "torch", "compiled")
"""Values of :attr:`FlowConfig.backend`."""
LOOKUPS = ("auto", "passes", "sorted")
"""Values of :attr:`FlowConfig.lookup`."""


@dataclass(frozen=True)
class FlowConfig(Config):
    """Parameters of :class:`~evtrack.flow.TripletFlow`.

    Attributes:
        sensor_size: ``(width, height)`` in pixels; ``None`` takes it from the first events.
        radius: search radius r in pixels: displacements ``d`` are all integer offsets on the
            square rings 1..r (``(2r+1)^2 - 1`` of them), so ``e_i`` lies up to ``2r`` px away.
        history: K, how many most recent events per pixel and polarity are kept and tried
            as ``e_j`` / ``e_i`` (K*K pairs per displacement).
        refractory_us: burst filter, µs: an event is skipped (not searched, not stored) when
            the previous event of its pixel has the same polarity and is at most this old
            (chained through skipped events). A moving edge fires a burst of same-polarity
            events per pixel; keeping the onsets makes the history hold edge arrival times,
            which the triplet timing test needs. The default (20 ms) keeps one onset per edge
            down to about 50 px/s for edges a pixel wide (a slower or blurred edge whose burst
            has gaps longer than this gives several onsets at different intensity levels,
            whose times do not move rigidly with the edge). 0 disables the filter.
        tolerance_us: absolute part of the constant-velocity tolerance ξ, in µs.
        tolerance_rel: relative part of ξ, as a fraction of ``t_k - t_i``; used at per-mille
            resolution (``round(1000 * tolerance_rel)``).
        min_speed: smallest plausible speed in px/s (> 0); slower candidates are dropped.
        max_speed: largest plausible speed in px/s; faster candidates are dropped.
        max_span_us: longest triplet, ``t_k - t_i`` in µs; 0 (the default): no bound beyond
            ``min_speed``. A triplet's flow is the mean velocity over its span, so it lags the
            present by about half the span. On the ``faster`` benchmark sequences, whose
            velocity changes within tens of ms, the unbounded RoI flow matched the true flow
            of 4-12 ms *earlier* best (``min_speed`` alone allows 300 ms spans at radius 3).
            For fast objects ``configs/flow_fast.yaml`` sets 40 ms with ``tolerance_rel``
            0.05: median relative RoI error 0.136 -> 0.092 on ``faster``, 0.116 -> 0.079 on
            ``regular`` (4 kHz renders); the tracker's flow (``TrackerConfig.flow``) uses
            both by default. It is not the flow's default because edges slower than
            ``2 |d| / max_span_us`` (50 px/s for the nearest neighbours at 40 ms) give no
            candidates: on tonic's slow DVXplorer sample recording (AEDAT4) it leaves
            4 RoI flows of 1,418. A bound much shorter than 40 ms leaves a slow RoI only
            near-tangent triplets, whose consensus can be wrong (20 ms: 3.3x the true flow on
            one slow sequence).
        roi_size: side of the square regions of interest, in pixels (the last row/column of
            RoIs is cut by the sensor border).
        window_us: length of the registration time windows in µs; windows are aligned on
            absolute time (window ``w`` covers ``[w * window_us, (w + 1) * window_us)``).
        min_support: a RoI window is reported only when at least this many of its events
            have a candidate.
        min_lines: a RoI window is reported only when at least this many of its events gave a
            constraint line (see :mod:`evtrack.flow.registration`: an event whose candidates
            near the registered flow come from two non-parallel displacements). A window
            without one reports a single event's candidate that no other displacement
            confirms; 0 reports it.
        fit_min_lines: the fewest constraint lines for the aperture test and the refinement
            (1 or 2). With fewer, the Eq. 3 candidate itself is reported as full flow. With 1,
            a window whose events give a single line reports that line's normal flow: one
            line measures only the flow across it, and its Eq. 3 candidate is one arbitrary
            point along it.
        max_lineless_share: when, among the RoI windows of one time window that pass the
            other report rules, the share without a constraint line is above this, that time
            window is judged strictly: its line-less RoI windows are refused and its one-line
            RoI windows report their line's normal flow (as with ``min_lines`` 1 and
            ``fit_min_lines`` 1, for that time window only). On a real sensor, whose
            timestamps jitter, most candidates match along one displacement only: on the ECD
            recordings, 75-78 % of the reported RoI windows of the slow poster and boxes
            clips had no line, and their flows erred by a median 50-63° and 3x in
            magnitude; simulated objects had 3-12 % such windows. 1 (the default): never.
        min_inlier_fraction: a RoI window is reported only when at least this fraction of
            the events in its data term agree with the registered flow (their candidate
            nearest to it lies within ``line_gate * |F|``; see
            :mod:`evtrack.flow.registration`). Events not caused by one rigid motion
            (shading changes on textureless faces, flicker, the first window after a reset)
            give unrelated candidates that rarely agree; their windows are refused instead
            of reported with an arbitrary flow. 0 reports every window.
        max_events_per_roi: cap on the events whose candidates enter the registration cost
            of one RoI window (the data term of Eq. 3). Above it, the events with the
            smallest hash of their stream index are kept: deterministic, independent of
            chunking, and without bias towards early or late events.
        max_hypotheses: cap on the candidate flows tried as the solution F' of one RoI
            window; above it, the candidates with the smallest hash are tried.
        aperture_ratio: a RoI flow is flagged as normal flow when the scatter of its events'
            constraint-line normals has eigenvalue ratio ``lambda_min / lambda_max`` below
            this value (all lines share one normal), see :mod:`evtrack.flow.registration`.
        refine: replace the Eq. 3 solution (one candidate, direction quantised to the integer
            displacements) by the robust intersection of the events' constraint lines.
        line_gate: an event gives a constraint line only if its candidate nearest to the
            Eq. 3 solution F lies within ``line_gate * |F|`` of it.
        refine_iters: IRLS iterations of the refinement.
        chunk_size: events handed to the batched search at once (bounds the sorting work).
            An update of several such pieces on the compiled backend searches the next piece
            in a worker thread while it registers the current one.
        block_size: events whose lookups are evaluated as one tensor operation; peak tensor
            sizes are ``block_size * (number of displacements) * (history + pass_repeats)``.
            ``None``: 16384 on CPU, 262144 on CUDA.
        pass_repeats: L, how many events of one pixel a conflict-free pass may hold. The
            ring buffer keeps ``history + pass_repeats`` slots per pixel and polarity; larger
            values mean fewer sequential passes but wider lookups. With the burst filter on,
            repeated onsets of one cell within a chunk are rare and 1 is fastest.
        lookup: how the tensor code finds each event's predecessors within its chunk.
            ``"passes"``: the chunk is cut into conflict-free passes (above) and a lookup is a
            gather of a cell's ring-buffer slots; a fast object re-fires its pixels within a
            chunk, so a chunk can need hundreds of passes, each a few dozen small kernels.
            ``"sorted"``: the whole chunk is one pass: its events are sorted by (cell,
            position) once and a lookup binary-searches that order (two searches per lookup,
            any number of events per cell); the rings take each cell's newest events at the
            chunk's end. ``"auto"``: sorted on CUDA, passes on CPU. Same candidates, bit for
            bit. The compiled CPU backend does not use it.
        pair_budget: largest number of (hypothesis, candidate) distances the registration
            evaluates at once (bounds its memory).
        device: torch device of the history and of all computation.
        backend: ``"auto"``: compiled kernels where they can run, else the batched tensor
            code. On CPU the kernels are :mod:`evtrack.flow.compiled` and
            :mod:`evtrack.flow.registration_compiled` (numba) for the search and the
            registration; on CUDA the search is the tensor code and the registration's
            per-group solve is one Triton kernel (:mod:`evtrack.flow.registration_triton`;
            Triton comes with PyTorch's CUDA builds). ``"torch"``: always the tensor code.
            ``"compiled"``: always the kernels (an error where they cannot run: without
            numba on CPU, without Triton on CUDA). All give the same candidates, the same
            RoIs with the same Eq. 3 solutions, costs and inlier counts, bit for bit; the
            refined flows agree to float rounding. On 2 CPU cores the kernels were 4-11x
            faster (``benchmarks/bench_flow_speed.py``). The choice is made by
            :func:`evtrack.flow.backends.resolve`.
    """

    sensor_size: tuple[int, int] | None = None
    radius: int = 3
    history: int = 2
    refractory_us: int = 20_000
    tolerance_us: int = 20
    tolerance_rel: float = 0.1
    min_speed: float = 20.0
    max_speed: float = 20_000.0
    max_span_us: int = 0
    roi_size: int = 32
    window_us: int = 2_000
    min_support: int = 5
    min_lines: int = 0
    fit_min_lines: int = 2
    max_lineless_share: float = 1.0
    min_inlier_fraction: float = 0.5
    max_events_per_roi: int = 64
    max_hypotheses: int = 48
    aperture_ratio: float = 0.05
    refine: bool = True
    line_gate: float = 0.35
    refine_iters: int = 5
    chunk_size: int = 200_000
    block_size: int | None = None
    pass_repeats: int = 1
    lookup: str = "auto"
    pair_budget: int = 4_000_000
    device: str = "cpu"
    backend: str = "auto"

    def __post_init__(self) -> None:
        super().__post_init__()

        def need(cond: bool, name: str, problem: str) -> None:
            if not cond:
                raise ConfigError(f"flow config field '{name}': {problem}")

        if self.sensor_size is not None:
            size = tuple(int(v) for v in self.sensor_size)
            need(len(size) == 2 and min(size) > 0, "sensor_size",
                 f"expected (width, height) > 0, got {self.sensor_size}")
            object.__setattr__(self, "sensor_size", size)
        for name in ("radius", "history", "roi_size", "window_us", "chunk_size",
                     "pass_repeats", "pair_budget", "max_events_per_roi", "max_hypotheses",
                     "refine_iters"):
            value = getattr(self, name)
            need(isinstance(value, int | np.integer) and not isinstance(value, bool) and value >= 1,
                 name, f"expected an integer >= 1, got {value!r}")
        need(self.block_size is None or (isinstance(self.block_size, int) and self.block_size >= 1),
             "block_size", f"expected None or an integer >= 1, got {self.block_size!r}")
        need(isinstance(self.refractory_us, int) and self.refractory_us >= 0, "refractory_us",
             f"expected an integer >= 0 (µs), got {self.refractory_us!r}")
        need(isinstance(self.max_span_us, int) and not isinstance(self.max_span_us, bool)
             and self.max_span_us >= 0, "max_span_us",
             f"expected an integer >= 0 (µs; 0: no bound), got {self.max_span_us!r}")
        need(isinstance(self.tolerance_us, int) and self.tolerance_us >= 0, "tolerance_us",
             f"expected an integer >= 0 (µs), got {self.tolerance_us!r}")
        need(isinstance(self.min_support, int) and self.min_support >= 1, "min_support",
             f"expected an integer >= 1, got {self.min_support!r}")
        need(isinstance(self.min_lines, int) and not isinstance(self.min_lines, bool)
             and self.min_lines >= 0, "min_lines",
             f"expected an integer >= 0, got {self.min_lines!r}")
        need(self.fit_min_lines in (1, 2) and not isinstance(self.fit_min_lines, bool),
             "fit_min_lines", f"expected 1 or 2, got {self.fit_min_lines!r}")
        need(isinstance(self.max_lineless_share, int | float)
             and not isinstance(self.max_lineless_share, bool)
             and 0.0 <= float(self.max_lineless_share) <= 1.0, "max_lineless_share",
             f"expected a share in [0, 1], got {self.max_lineless_share!r}")
        need(0.0 <= float(self.tolerance_rel) < 1.0, "tolerance_rel",
             f"expected a fraction in [0, 1), got {self.tolerance_rel!r}")
        need(float(self.min_speed) > 0.0, "min_speed", f"must be > 0 px/s, got {self.min_speed}")
        need(float(self.max_speed) > float(self.min_speed), "max_speed",
             f"must exceed min_speed ({self.min_speed}), got {self.max_speed}")
        need(isinstance(self.refine, bool), "refine", f"expected true/false, got {self.refine!r}")
        need(self.lookup in LOOKUPS, "lookup", f"expected one of {LOOKUPS}, got {self.lookup!r}")
        need(self.backend in BACKENDS, "backend",
             f"expected one of {BACKENDS}, got {self.backend!r}")
        need(float(self.line_gate) > 0.0, "line_gate", f"must be > 0, got {self.line_gate}")
        need(0.0 <= float(self.min_inlier_fraction) <= 1.0, "min_inlier_fraction",
             f"expected a fraction in [0, 1], got {self.min_inlier_fraction!r}")
        need(0.0 <= float(self.aperture_ratio) <= 1.0, "aperture_ratio",
             f"expected a value in [0, 1], got {self.aperture_ratio}")
        longest = 2.0 * math.hypot(self.radius, self.radius) * US_PER_S / float(self.min_speed)
        need(longest < MAX_DT_US, "min_speed",
             f"{self.min_speed} px/s allows triplets spanning {longest / 1e6:.0f} s; the "
             f"history resolves at most {MAX_DT_US / 1e6:.0f} s")

    # ------------------------------------------------------------------ derived values
    @property
    def tolerance_permille(self) -> int:
        """The relative tolerance in per-mille, as used by the integer test."""
        return int(round(1000.0 * float(self.tolerance_rel)))

    @property
    def slots(self) -> int:
        """Ring-buffer slots per pixel and polarity: ``history + pass_repeats``."""
        return self.history + self.pass_repeats

    def resolved_block_size(self, device_type: str) -> int:
        """:attr:`block_size`, or its device-dependent default."""
        if self.block_size is not None:
            return int(self.block_size)
        return 262_144 if device_type == "cuda" else 16_384

    def resolved_lookup(self, device_type: str) -> str:
        """:attr:`lookup`, with ``"auto"`` resolved for ``device_type``: ``"sorted"`` or
        ``"passes"``."""
        if self.lookup != "auto":
            return self.lookup
        return "sorted" if device_type == "cuda" else "passes"

    def replace(self, **changes: Any) -> FlowConfig:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------ loading
    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None, source: str = "flow config"
                  ) -> FlowConfig:
        """Build from a mapping by the rules of :mod:`evtrack.configs`; missing fields keep
        their defaults, unknown ones are errors naming ``source`` and the field."""
        return configs.from_dict(cls, data, source)

    @classmethod
    def from_yaml(cls, path: str | Path) -> FlowConfig:
        """Load from a YAML file: either the fields at top level or under a ``flow:`` key."""
        data = configs.read_yaml(path)
        if isinstance(data.get("flow"), Mapping):
            data = data["flow"]
        return cls.from_dict(data, str(path))


def search_offsets(radius: int) -> np.ndarray:
    """The displacements ``d`` searched, in their canonical order.

    Args:
        radius: r >= 1.

    Returns:
        (D, 2) int64 array of ``(dx, dy)``: every integer offset with Chebyshev norm in
        ``1..r``, ordered by ring, then ``dy``, then ``dx``. ``D = (2r+1)^2 - 1``.
    """
    rows = [(max(abs(dx), abs(dy)), dy, dx)
            for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)
            if (dx, dy) != (0, 0)]
    rows.sort()
    return np.array([(dx, dy) for _, dy, dx in rows], dtype=np.int64).reshape(-1, 2)


def _speed_ok(dist_px: float, dt_us: int, lo: float, hi: float) -> bool:
    speed = dist_px * US_PER_S / dt_us
    return lo <= speed <= hi


def dt_bounds_us(offsets: np.ndarray, min_speed: float, max_speed: float,
                 max_span_us: int = 0) -> np.ndarray:
    """Integer bounds on ``t_k - t_i`` equivalent to the speed and span tests of each displacement.

    The speed of a candidate from displacement ``d`` is ``|2d| * 1e6 / (t_k - t_i)`` px/s,
    evaluated in float64 as ``math.hypot(2dx, 2dy) * 1e6 / dt``. Because it decreases with
    ``dt``, ``min_speed <= speed <= max_speed`` holds exactly for ``lo <= dt <= hi``; the
    bounds are found from the closed form and corrected by evaluating that same test. With
    ``max_span_us > 0``, ``hi`` is at most ``max_span_us`` as well.

    Returns:
        (D, 2) int64 array ``[lo, hi]`` in µs (``lo >= 1``; ``lo > hi`` when none fits).
    """
    out = np.zeros((len(offsets), 2), dtype=np.int64)
    for n, (dx, dy) in enumerate(np.asarray(offsets).tolist()):
        dist = math.hypot(2 * dx, 2 * dy)
        lo = max(1, math.ceil(dist * US_PER_S / max_speed) - 2)
        while dist * US_PER_S / lo > max_speed:
            lo += 1
        hi = max(lo, math.floor(dist * US_PER_S / min_speed) + 2)
        while hi > lo and not _speed_ok(dist, hi, min_speed, max_speed):
            hi -= 1
        if max_span_us > 0:
            hi = min(hi, int(max_span_us))
        if not _speed_ok(dist, lo, min_speed, max_speed) or hi < lo:
            lo, hi = 1, 0
        out[n] = (lo, hi)
    return out
