"""The registration's compiled CPU backend (numba): :class:`CompiledRegistration`.

The tensor registration (:mod:`evtrack.flow.registration_tensor`) is a chain of sorts,
scatters and masks over all candidates of a batch; on a CPU its cost is mostly the passes and
the per-call overhead, not arithmetic (the tracker registers a few thousand events every few
milliseconds). Here the same rule runs group by group in compiled loops:

1. :func:`~evtrack.flow.arrange_kernels.arrange_kernel`: the data-term cap, the kept
   candidates laid out by group with events in stream order, and the hypotheses in rank
   order;
2. :func:`~evtrack.flow.solve_kernels.solve_kernel`, in parallel over the groups: the exact
   integer Eq. 3 cost of the hypotheses, then the events' constraint lines, the inlier count
   and the IRLS intersection of the lines;
3. for the flow's closed windows, their reported rows (:func:`_report_rows`) in the same
   compiled call.

Everything up to the lines is integer or exactly specified float arithmetic (float32 squared
distances with separate IEEE operations,
:func:`~evtrack.flow.registration_tensor.rounded_distance`, float64 comparisons), so
``full_flow``, ``cost``, ``used_events``, ``inliers`` and ``lines`` equal the tensor path's
bit for bit. The refined ``flow``, ``ratio`` and ``normal_dir`` go through ``sqrt``,
``atan2``, ``cos`` and ``sin`` and a summation order of their own; they agree with the tensor
path to float rounding (``tests/flow/test_flow_backends.py`` pins both).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evtrack.flow.arrange_kernels import arrange_kernel, group_positions
from evtrack.flow.constants import COST_SCALE, IRLS_DELTA, PARALLEL_EPS, Q_MAX
from evtrack.flow.numba_support import available, kernel, numba, torch_thread_count
from evtrack.flow.solution import GroupSolution
from evtrack.flow.solve_kernels import solve_kernel

__all__ = ["CompiledRegistration"]

_POSITION_SLACK = 8
_POSITION_FLOOR = 65_536
"""Key ranges up to ``_POSITION_SLACK * count + _POSITION_FLOOR`` get a dense position table
(as :func:`evtrack.flow.pending.positions`)."""


@kernel()
def _report_rows(keys, support, n_events, has, full, best_cost, used_events, inliers, lines,
                 fit_flow, ratio, major, normal_speed, n_roi, window_us, centres, cost_scale,
                 aperture_ratio, min_support, min_inlier_fraction, min_lines, fit_min_lines,
                 max_lineless_share):
    """The reported rows of registered groups (CPU, compiled): what
    :func:`~evtrack.flow.registration.register_groups` (with ``refine``) makes of the compiled
    registration's outputs, the report test of ``TripletFlow._finalise`` and the rows of
    ``TripletFlow._rows``, in one pass and with the same float32 / float64 operations.
    ``centres``: (R, 2) float32 RoI centres; ``n_roi`` RoIs per window.

    Returns ``reported`` (G,) and the rows' ``xy, t, flow, support, cost, normal, normal_dir,
    full_flow, n_events, roi, window``."""
    n_groups = keys.shape[0]
    reported = np.empty(n_groups, np.bool_)
    fit_from = np.empty(n_groups, np.int64)  # the lines a group's fit needs
    for g in range(n_groups):
        agree = np.float64(inliers[g]) >= min_inlier_fraction * np.float64(used_events[g])
        reported[g] = support[g] >= min_support and not np.isnan(full[g, 0]) and agree
    # the line rules (evtrack.flow.line_rules), per time window (keys are sorted)
    n_rows = 0
    a = 0
    while a < n_groups:
        w = keys[a] // n_roi
        b = a
        passing = 0
        lineless = 0
        while b < n_groups and keys[b] // n_roi == w:
            if reported[b]:
                passing += 1
                lineless += lines[b] == 0
            b += 1
        strict = (max_lineless_share < 1.0
                  and np.float64(lineless) > max_lineless_share * np.float64(passing))
        for g in range(a, b):
            reported[g] = (reported[g] and lines[g] >= min_lines
                           and not (strict and lines[g] == 0))
            fit_from[g] = 1 if strict else fit_min_lines
            n_rows += reported[g]
        a = b
    xy = np.empty((n_rows, 2), np.float32)
    t = np.empty(n_rows, np.int64)
    flow = np.empty((n_rows, 2), np.float32)
    sup = np.empty(n_rows, np.int64)
    cost = np.empty(n_rows, np.float32)
    normal = np.empty(n_rows, np.bool_)
    normal_dir = np.empty((n_rows, 2), np.float32)
    full_flow = np.empty((n_rows, 2), np.float32)
    n_ev = np.empty(n_rows, np.int64)
    roi = np.empty(n_rows, np.int64)
    window = np.empty(n_rows, np.int64)
    r = 0
    for g in range(n_groups):
        if not reported[g]:
            continue
        w = keys[g] // n_roi
        roi[r] = keys[g] - w * n_roi
        window[r] = w
        xy[r, 0], xy[r, 1] = centres[roi[r], 0], centres[roi[r], 1]
        t[r] = w * window_us + window_us // 2
        sup[r] = support[g]
        n_ev[r] = n_events[g]
        full_flow[r, 0], full_flow[r, 1] = full[g, 0], full[g, 1]
        cost[r] = (np.float32(np.float64(best_cost[g]) / cost_scale
                              / np.float64(max(used_events[g], 1))) if has[g] else np.nan)
        fitted = has[g] and lines[g] >= fit_from[g]
        normal[r] = fitted and ratio[g] < aperture_ratio
        nx, ny = np.float32(major[g, 0]), np.float32(major[g, 1])
        if normal[r]:
            speed = np.float32(normal_speed[g])
            flow[r, 0], flow[r, 1] = speed * nx, speed * ny
            normal_dir[r, 0], normal_dir[r, 1] = nx, ny
        else:
            if fitted:
                flow[r, 0], flow[r, 1] = np.float32(fit_flow[g, 0]), np.float32(fit_flow[g, 1])
            else:
                flow[r, 0], flow[r, 1] = full[g, 0], full[g, 1]
            normal_dir[r, 0] = normal_dir[r, 1] = np.nan
        r += 1
    return reported, xy, t, flow, sup, cost, normal, normal_dir, full_flow, n_ev, roi, window


@kernel()
def _register_kernel(group, seq, ordinal, flow, n_groups, max_events, max_hypotheses,
                     n_ordinals, cost_scale, q_max, parallel_eps, line_gate, irls_delta,
                     refine_iters, threads):
    """Steps 1 and 2 of the module docstring: ``(used events per group,)`` + the outputs of
    :func:`~evtrack.flow.solve_kernels.solve_kernel`."""
    (c_x, c_y, c_event, counts, c_start, ev_per_group, h_cand, h_start,
     h_count) = arrange_kernel(group, seq, ordinal, flow, n_groups, max_events,
                                max_hypotheses, n_ordinals)
    return (ev_per_group,) + solve_kernel(h_cand, h_start, h_count, c_x, c_y, c_event,
                                           counts, c_start, ev_per_group, cost_scale, q_max,
                                           parallel_eps, line_gate, irls_delta, refine_iters,
                                           threads)


@kernel()
def _register_closed_kernel(keys, gkey, seq, ordinal, flow, support, n_events, centres, n_roi,
                            window_us, max_events, max_hypotheses, n_ordinals, line_gate,
                            refine_iters, aperture_ratio, min_support, min_inlier_fraction,
                            min_lines, fit_min_lines, max_lineless_share, cost_scale, q_max,
                            parallel_eps, irls_delta, slack, floor, threads):
    group = group_positions(keys, gkey, slack, floor)
    (ev_per_group, full, has, best_cost, inliers, lines, fit_flow, ratio, major,
     normal_speed) = _register_kernel(group, seq, ordinal, flow, keys.shape[0], max_events,
                                      max_hypotheses, n_ordinals, cost_scale, q_max,
                                      parallel_eps, line_gate, irls_delta, refine_iters,
                                      threads)
    (reported, xy, t, flow_out, sup, cost, normal, normal_dir, full_flow, n_ev, roi,
     window) = _report_rows(keys, support, n_events, has, full, best_cost, ev_per_group,
                            inliers, lines, fit_flow, ratio, major, normal_speed, n_roi,
                            window_us, centres, cost_scale, aperture_ratio, min_support,
                            min_inlier_fraction, min_lines, fit_min_lines,
                            max_lineless_share)
    return (group, reported, full, xy, t, flow_out, sup, cost, normal, normal_dir, full_flow,
            n_ev, roi, window)


class CompiledRegistration:
    """The registration's per-group solve in compiled loops (CPU, numba; see the module
    docstring). The kernels run on ``torch.get_num_threads()`` threads.

    Raises:
        RuntimeError: at a call, where numba is not installed.
    """

    reports_rows: bool = True
    """:meth:`register_closed` makes the flow's reported rows in the same compiled call (see
    :class:`~evtrack.flow.backends.RegistrationBackend`)."""

    def solve(self, group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, g_count: int,
              max_events: int, max_hypotheses: int, pair_budget: int, line_gate: float,
              refine_iters: int, n_ordinals: int) -> GroupSolution:
        """The caps, Eq. 3, the constraint lines and their fit (CPU tensors in and out).

        Args: as :func:`evtrack.flow.registration.register_groups` (``group`` in
        ``[0, g_count)``, candidates of one event consecutive, events in stream order);
        ``pair_budget`` is not needed here.
        """
        _need_numba()
        with torch_thread_count():
            as64 = [np.ascontiguousarray(v.detach().cpu().numpy(), dtype=np.int64)
                    for v in (group, seq, ordinal)]
            (used_events, full, has, best_cost, inliers, lines, fit_flow, ratio, major,
             normal_speed) = (torch.from_numpy(a) for a in _register_kernel(
                *as64, np.ascontiguousarray(flow.detach().cpu().numpy(), dtype=np.float32),
                int(g_count), int(max_events), int(max_hypotheses), int(n_ordinals),
                float(COST_SCALE), float(Q_MAX), float(PARALLEL_EPS), float(line_gate),
                float(IRLS_DELTA), int(refine_iters), numba.get_num_threads()))
        return GroupSolution(has=has, full=full, best_cost=best_cost, used_events=used_events,
                             inliers=inliers, lines=lines, fit_flow=fit_flow.to(torch.float32),
                             ratio=ratio, major=major.to(torch.float32),
                             normal_speed=normal_speed.to(torch.float32))

    def register_closed(self, keys: np.ndarray, gkey: np.ndarray, seq: np.ndarray,
                        ordinal: np.ndarray, flow: np.ndarray, support: np.ndarray,
                        n_events: np.ndarray, centres: np.ndarray, n_roi: int, window_us: int,
                        max_events: int, max_hypotheses: int, n_ordinals: int,
                        line_gate: float, refine_iters: int, aperture_ratio: float,
                        min_support: int, min_inlier_fraction: float,
                        min_lines: int = 0, fit_min_lines: int = 2,
                        max_lineless_share: float = 1.0) -> tuple[np.ndarray, ...]:
        """Register the closed RoI windows of the flow and make their reported rows, in one
        compiled call (CPU): the group position of each candidate, the caps and Eq. 3
        (:mod:`evtrack.flow.arrange_kernels`, :mod:`evtrack.flow.solve_kernels`), the line
        fit and the rows (:func:`_report_rows`, with the refined flow).

        Args:
            keys: (G,) sorted distinct group keys ``window * n_roi + roi`` of the closed
                windows.
            gkey: (M,) int64 group key of each candidate (each in ``keys``); candidates of one
                event consecutive, events in stream order.
            seq, ordinal: (M,) int64 stream index of the candidate's event, its ordinal
                (``< n_ordinals``).
            flow: (M, 2) float32 candidate flows, px/s.
            support, n_events: (G,) int64 events with candidates, all events, per group.
            centres: (n_roi, 2) float32 RoI centres, px.
            n_roi, window_us: RoIs per window, window length (µs).
            max_events, max_hypotheses, n_ordinals, line_gate, refine_iters: as
                :func:`evtrack.flow.registration.register_groups`.
            aperture_ratio, min_support, min_inlier_fraction, min_lines, fit_min_lines,
                max_lineless_share: the flow config's report rules.

        Returns:
            ``(position (M,), reported (G,), full (G, 2), xy, t, flow, support, cost, normal,
            normal_dir, full_flow, n_events, roi, window)``, the last eleven over the reported
            rows (the :class:`~evtrack.flow.result.FlowResult` columns).

        Raises:
            ValueError: an ordinal ``>= n_ordinals``.
        """
        _need_numba()
        if ordinal.shape[0] and int(ordinal.max()) >= n_ordinals:
            raise ValueError(f"candidate ordinals must be < n_ordinals ({n_ordinals})")
        as64 = [np.ascontiguousarray(v, dtype=np.int64)
                for v in (keys, gkey, seq, ordinal, support, n_events)]
        with torch_thread_count():
            return _register_closed_kernel(
                *as64[:4], np.ascontiguousarray(flow, dtype=np.float32), *as64[4:],
                np.ascontiguousarray(centres, dtype=np.float32), int(n_roi), int(window_us),
                int(max_events), int(max_hypotheses), int(n_ordinals), float(line_gate),
                int(refine_iters), float(aperture_ratio), int(min_support),
                float(min_inlier_fraction), int(min_lines), int(fit_min_lines),
                float(max_lineless_share),
                float(COST_SCALE), float(Q_MAX),
                float(PARALLEL_EPS), float(IRLS_DELTA), _POSITION_SLACK, _POSITION_FLOOR,
                numba.get_num_threads())


def _need_numba() -> None:
    if not available():
        raise RuntimeError("the compiled flow backend needs numba (pip install numba)")
