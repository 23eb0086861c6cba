"""The registration's Triton backend (CUDA): :class:`TritonRegistration`, the per-group
solve as one Triton kernel.

The tensor registration (:func:`evtrack.flow.registration.register_groups`) evaluates Eq. 3 in
batches of groups padded to dense ``(groups, hypotheses, candidates)`` blocks, then finds the
events' constraint lines and fits them with a few dozen more kernels per IRLS iteration. On a
GPU that is hundreds of small kernel launches and a host synchronisation per batch: the flow
becomes bound by the host, not by the GPU. Here one program per group (RoI window) does all
of it, as the compiled CPU form (:mod:`evtrack.flow.registration_compiled`) does per thread:

1. the exact integer cost ``sum_events min_c round(|F_h - F_c| * COST_SCALE)`` of every
   hypothesis at once (a vector over the hypotheses; the events in turn, each event's
   candidates in blocks), and the arg-min with ties to the smallest rank;
2. each event's constraint line through its candidate nearest to ``F`` and its nearest
   candidate from a non-parallel displacement (nearness by the rounded distance, ties to the
   earlier candidate), the inlier count;
3. the IRLS intersection of the lines and the aperture test's eigen-decomposition.

Steps 1 and 2 use the exactly specified arithmetic of the tensor path (float32 squared
distances with separate IEEE operations, which is why the kernel is compiled without fused
multiply-adds; the rounding of :func:`~evtrack.flow.registration.rounded_distance`; float64
comparisons), so ``full_flow``, ``cost``, ``used_events``, ``inliers`` and ``lines`` equal the
tensor path's bit for bit. Step 3 sums in its own order and finds the dominant normal by
half-angle formulas instead of ``atan2``, ``cos`` and ``sin``: ``flow``, ``ratio`` and
``normal_dir`` agree to float rounding.

Triton ships with PyTorch's CUDA builds; without it (or on CPU) the tensor path runs. Its
interpreter (``TRITON_INTERPRET=1``) runs the same kernel on CPU tensors, which is how the
tests check it on machines without a GPU.
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from evtrack.flow.constants import COST_SCALE, IRLS_DELTA, PARALLEL_EPS, Q_MAX, RANK_BITS
from evtrack.flow.registration_tensor import Arrangement, TensorRegistration, arrange
from evtrack.flow.solution import GroupSolution

try:  # optional: present with PyTorch's CUDA builds
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - exercised where triton is missing
    triton = None

__all__ = ["TritonRegistration", "available", "fits", "solve_groups", "MAX_CAP"]

_INT64_MAX = (1 << 63) - 1
MAX_CAP = 256
"""Largest ``max_events_per_roi`` and ``max_hypotheses`` the kernel takes: one program holds
a group's hypotheses and its events' lines in registers, padded to a power of two."""


def available(device_type: str) -> bool:
    """Whether the kernel can run on ``device_type``: ``"cuda"`` with Triton installed, or
    any device under Triton's interpreter (``TRITON_INTERPRET=1``, for tests)."""
    if triton is None:
        return False
    return device_type == "cuda" or os.environ.get("TRITON_INTERPRET") == "1"


if triton is not None:
    _BIG = tl.constexpr(_INT64_MAX)

    @triton.jit
    def _rounded(d2, cost_scale, q_max):
        """``rounded_distance`` of float32 squared distances (a block), as int64."""
        dd = d2.to(tl.float64) * (cost_scale * cost_scale)
        capped = dd >= q_max * q_max
        dd = tl.where(capped, 0.0, dd)
        n = tl.floor(tl.sqrt(dd) + 0.5)
        up = (n + 0.5) * (n + 0.5)
        down = (n - 0.5) * (n - 0.5)
        n = n + tl.where(dd > up, 1.0, 0.0) - tl.where((dd < down) & (n > 0.0), 1.0, 0.0)
        up = (n + 0.5) * (n + 0.5)
        down = (n - 0.5) * (n - 0.5)
        odd = (n - 2.0 * tl.floor(n * 0.5)) == 1.0  # a tie goes to the even neighbour
        n = n + tl.where(odd & (dd == up), 1.0, 0.0) - tl.where(odd & (dd == down), 1.0, 0.0)
        return tl.where(capped, q_max, n).to(tl.int64)

    @triton.jit
    def _solve_kernel(c_x, c_y, ev_ptr, ev_start, ev_count, h_idx, h_first, h_count,
                      out_chosen, out_cost, out_inliers, out_lines, out_fit, out_ratio,
                      out_major, out_speed, cost_scale, q_max, eps2, gate2, irls_delta,
                      refine_iters, BLOCK_H: tl.constexpr, BLOCK_C: tl.constexpr,
                      BLOCK_E: tl.constexpr, RANK_BITS: tl.constexpr):
        g = tl.program_id(0)
        nh = tl.load(h_count + g)
        if nh > 0:
            h0 = tl.load(h_first + g)
            e0 = tl.load(ev_start + g)
            ne = tl.load(ev_count + g)
            # --- 1. the cost of every hypothesis, then the arg-min (cost, rank)
            hr = tl.arange(0, BLOCK_H)
            hmask = hr < nh
            hid = tl.load(h_idx + h0 + hr, mask=hmask, other=0)
            hx = tl.load(c_x + hid, mask=hmask, other=0.0)
            hy = tl.load(c_y + hid, mask=hmask, other=0.0)
            total = tl.zeros([BLOCK_H], dtype=tl.int64)
            for e in range(e0, e0 + ne):
                c0 = tl.load(ev_ptr + e)
                c1 = tl.load(ev_ptr + e + 1)
                m = tl.full([BLOCK_H], float("inf"), tl.float32)
                for cb in range(c0, c1, BLOCK_C):
                    cr = cb + tl.arange(0, BLOCK_C)
                    cm = cr < c1
                    cx = tl.load(c_x + cr, mask=cm, other=0.0)
                    cy = tl.load(c_y + cr, mask=cm, other=0.0)
                    dx = hx[:, None] - cx[None, :]
                    dy = hy[:, None] - cy[None, :]
                    d2 = dx * dx
                    d2 = d2 + dy * dy
                    d2 = tl.where(cm[None, :], d2, float("inf"))
                    m = tl.minimum(m, tl.min(d2, axis=1))
                total += _rounded(m, cost_scale, q_max)
            combo = (total << RANK_BITS) | hr.to(tl.int64)
            combo = tl.where(hmask, combo, _BIG)
            best = tl.min(combo, axis=0)
            best_rank = best & ((1 << RANK_BITS) - 1)
            chosen = tl.load(h_idx + h0 + best_rank)
            fx = tl.load(c_x + chosen)
            fy = tl.load(c_y + chosen)
            tl.store(out_chosen + g, chosen)
            tl.store(out_cost + g, best >> RANK_BITS)
            # --- 2. one constraint line per event that agrees with F
            f2 = fx * fx
            f2 = f2 + fy * fy
            lim2 = gate2 * tl.maximum(f2.to(tl.float64), 1.0)
            er = tl.arange(0, BLOCK_E)
            ln_x = tl.zeros([BLOCK_E], dtype=tl.float64)
            ln_y = tl.zeros([BLOCK_E], dtype=tl.float64)
            ln_s = tl.zeros([BLOCK_E], dtype=tl.float64)
            ln_ok = tl.zeros([BLOCK_E], dtype=tl.int32)
            inliers = tl.zeros([BLOCK_E], dtype=tl.int32)
            for j in range(0, ne):
                c0 = tl.load(ev_ptr + e0 + j)
                c1 = tl.load(ev_ptr + e0 + j + 1)
                best1 = e0 * 0 + _BIG  # an int64 scalar
                for cb in range(c0, c1, BLOCK_C):  # nearest to F: smallest (q, index)
                    cr = cb + tl.arange(0, BLOCK_C)
                    cm = cr < c1
                    cx = tl.load(c_x + cr, mask=cm, other=0.0)
                    cy = tl.load(c_y + cr, mask=cm, other=0.0)
                    dx = cx - fx
                    dy = cy - fy
                    d2 = dx * dx
                    d2 = d2 + dy * dy
                    q = _rounded(d2, cost_scale, q_max)
                    key = tl.where(cm, (q << 32) | cr.to(tl.int64), _BIG)
                    best1 = tl.minimum(best1, tl.min(key, axis=0))
                i1 = best1 & 0xFFFFFFFF
                a_x32 = tl.load(c_x + i1)
                a_y32 = tl.load(c_y + i1)
                dx1 = a_x32 - fx
                dy1 = a_y32 - fy
                d2_1 = dx1 * dx1
                d2_1 = d2_1 + dy1 * dy1
                agree = d2_1.to(tl.float64) <= lim2
                ax = a_x32.to(tl.float64)
                ay = a_y32.to(tl.float64)
                a2 = ax * ax + ay * ay
                best2 = e0 * 0 + _BIG
                for cb in range(c0, c1, BLOCK_C):  # nearest to F not parallel to a
                    cr = cb + tl.arange(0, BLOCK_C)
                    cm = cr < c1
                    cx = tl.load(c_x + cr, mask=cm, other=0.0)
                    cy = tl.load(c_y + cr, mask=cm, other=0.0)
                    bx = cx.to(tl.float64)
                    by = cy.to(tl.float64)
                    cross = bx * ay - by * ax
                    nonpar = cross * cross > (eps2 * (bx * bx + by * by)) * a2
                    dx = cx - fx
                    dy = cy - fy
                    d2 = dx * dx
                    d2 = d2 + dy * dy
                    q = _rounded(d2, cost_scale, q_max)
                    key = tl.where(cm & nonpar, (q << 32) | cr.to(tl.int64), _BIG)
                    best2 = tl.minimum(best2, tl.min(key, axis=0))
                ok = agree & (best2 != _BIG)
                i2 = tl.where(best2 != _BIG, best2 & 0xFFFFFFFF, i1)
                tx = ax - tl.load(c_x + i2).to(tl.float64)
                ty = ay - tl.load(c_y + i2).to(tl.float64)
                length = tl.maximum(tl.sqrt(tx * tx + ty * ty), 1e-30)
                nx = -ty / length
                ny = tx / length
                s = nx * ax + ny * ay
                sign = tl.where(s < 0.0, -1.0, 1.0)
                here = er == j
                ln_x = tl.where(here, nx * sign, ln_x)
                ln_y = tl.where(here, ny * sign, ln_y)
                ln_s = tl.where(here, s * sign, ln_s)
                ln_ok = tl.where(here, ok.to(tl.int32), ln_ok)
                inliers = tl.where(here, agree.to(tl.int32), inliers)
            count = tl.sum(ln_ok, axis=0)
            tl.store(out_inliers + g, tl.sum(inliers, axis=0).to(tl.int64))
            tl.store(out_lines + g, count.to(tl.int64))
            # --- 3. IRLS intersection of the lines, from the Eq. 3 solution
            vx = fx.to(tl.float64)
            vy = fy.to(tl.float64)
            delta = irls_delta * tl.maximum(tl.sqrt(vx * vx + vy * vy), 1.0)
            use = ln_ok != 0
            zero = vx * 0.0  # float64 scalars carried through the loop
            ratio = zero + 1.0
            mx = zero + 1.0
            my = zero
            speed = zero
            for _ in range(0, refine_iters):
                r = ln_x * vx + ln_y * vy - ln_s
                w = tl.where(use, 1.0 / tl.maximum(tl.abs(r), delta), 0.0)
                a = tl.sum(w * (ln_x * ln_x), axis=0)
                b = tl.sum(w * (ln_x * ln_y), axis=0)
                c = tl.sum(w * (ln_y * ln_y), axis=0)
                r0 = tl.sum((w * ln_s) * ln_x, axis=0)
                r1 = tl.sum((w * ln_s) * ln_y, axis=0)
                half_tr = 0.5 * (a + c)
                rad = tl.sqrt((0.5 * (a - c)) * (0.5 * (a - c)) + b * b)
                l_max = half_tr + rad
                l_min = half_tr - rad
                ratio = tl.where(l_max > 0.0,
                                 tl.maximum(l_min / tl.maximum(l_max, 1e-300), 0.0), 1.0)
                # the unit eigenvector of l_max at theta = atan2(2 b, a - c) / 2 in
                # [-pi/2, pi/2] (as the tensor path), by half-angle formulas without
                # cancellation: cos(2 theta) = c2, sin(2 theta) = s2
                two_rad = 2.0 * rad
                c2 = tl.where(two_rad > 0.0, (a - c) / tl.where(two_rad > 0.0, two_rad, 1.0),
                              1.0)
                s2 = tl.where(two_rad > 0.0, (2.0 * b) / tl.where(two_rad > 0.0, two_rad, 1.0),
                              0.0)
                cos_small = tl.sqrt((1.0 + c2) * 0.5)  # |theta| <= pi/4: cos >= 0.7
                sin_big = tl.where(s2 < 0.0, -1.0, 1.0) * tl.sqrt((1.0 - c2) * 0.5)
                small = c2 >= 0.0
                mx = tl.where(small, cos_small,
                              tl.abs(s2) / tl.maximum(2.0 * tl.abs(sin_big), 1e-300))
                my = tl.where(small, s2 / tl.maximum(2.0 * cos_small, 1e-300), sin_big)
                speed = (mx * r0 + my * r1) / tl.maximum(l_max, 1e-300)
                det = a * c - b * b
                solvable = (count >= 2) & (det > 1e-12 * tl.maximum(l_max, 1e-300)
                                           * tl.maximum(l_max, 1e-300))
                safe = tl.where(det != 0.0, det, 1.0)
                vx_new = (c * r0 - b * r1) / safe
                vy_new = (a * r1 - b * r0) / safe
                vx = tl.where(solvable, vx_new, vx)
                vy = tl.where(solvable, vy_new, vy)
            tl.store(out_fit + 2 * g, vx)
            tl.store(out_fit + 2 * g + 1, vy)
            tl.store(out_ratio + g, ratio)
            tl.store(out_major + 2 * g, mx)
            tl.store(out_major + 2 * g + 1, my)
            tl.store(out_speed + g, speed)


def fits(max_events: int, max_hypotheses: int) -> bool:
    """Whether caps of this size fit one program (at most :data:`MAX_CAP` each); larger caps
    run the tensor registration."""
    return 1 <= int(max_events) <= MAX_CAP and 1 <= int(max_hypotheses) <= MAX_CAP


def solve_groups(c_flow: Tensor, ev_ptr: Tensor, ev_start: Tensor, ev_per_group: Tensor,
                 h_idx: Tensor, h_first: Tensor, h_count: Tensor, max_events: int,
                 max_hypotheses: int, cost_scale: float, q_max: int, parallel_eps: float,
                 line_gate: float, irls_delta: float, refine_iters: int, rank_bits: int
                 ) -> dict[str, Tensor]:
    """Eq. 3, the constraint lines and their fit for every group, one program per group.

    Args:
        c_flow: (M, 2) float32 kept candidate flows (px/s), grouped by group, events
            contiguous and in stream order within a group.
        ev_ptr: (E + 1,) int64 first candidate of each kept event, then M.
        ev_start, ev_per_group: (G,) int64 first kept event of each group and their number
            (at most ``max_events``).
        h_idx: (H,) int64 candidate index of each hypothesis, grouped by group, in rank order.
        h_first, h_count: (G,) int64 first hypothesis of each group and their number (at
            most ``max_hypotheses``).
        cost_scale, q_max, parallel_eps, line_gate, irls_delta, refine_iters, rank_bits: the
            registration's constants.

    Returns:
        (G,)-leading tensors: ``chosen`` (int64 candidate index of ``F``; undefined where
        ``h_count == 0``), ``best_cost`` (int64 scaled), ``inliers``, ``lines``, ``fit_flow``
        (float64 (G, 2)), ``ratio``, ``major`` (float64 (G, 2)), ``normal_speed``.
    """
    if triton is None:
        raise RuntimeError("the Triton registration needs triton (it comes with PyTorch's "
                           "CUDA builds)")
    dev = c_flow.device
    g_count = h_count.shape[0]
    i64 = {"dtype": torch.int64, "device": dev}
    f64 = {"dtype": torch.float64, "device": dev}
    out = {"chosen": torch.zeros(g_count, **i64), "best_cost": torch.zeros(g_count, **i64),
           "inliers": torch.zeros(g_count, **i64), "lines": torch.zeros(g_count, **i64),
           "fit_flow": torch.zeros(g_count, 2, **f64), "ratio": torch.ones(g_count, **f64),
           "major": torch.zeros(g_count, 2, **f64), "normal_speed": torch.zeros(g_count, **f64)}
    out["major"][:, 0] = 1.0  # the tensor path's direction where there are no lines
    if g_count == 0:
        return out
    c_x = c_flow[:, 0].contiguous()
    c_y = c_flow[:, 1].contiguous()
    block_h = triton.next_power_of_2(max(int(max_hypotheses), 2))
    block_e = triton.next_power_of_2(max(int(max_events), 2))
    _solve_kernel[(g_count,)](
        c_x, c_y, ev_ptr, ev_start, ev_per_group, h_idx, h_first, h_count,
        out["chosen"], out["best_cost"], out["inliers"], out["lines"], out["fit_flow"],
        out["ratio"], out["major"], out["normal_speed"], float(cost_scale), float(q_max),
        float(parallel_eps) * float(parallel_eps), float(line_gate) * float(line_gate),
        float(irls_delta), max(1, int(refine_iters)),
        BLOCK_H=block_h, BLOCK_C=16, BLOCK_E=block_e, RANK_BITS=rank_bits,
        **({} if os.environ.get("TRITON_INTERPRET") == "1" else {"enable_fp_fusion": False}))
    return out


class TritonRegistration:
    """The registration's per-group solve by the Triton kernel (CUDA; any device under
    Triton's interpreter): the tensor code's caps
    (:func:`~evtrack.flow.registration_tensor.arrange`), then one program per group, without
    host synchronisation. Caps above :data:`MAX_CAP` run the tensor solve instead."""

    reports_rows: bool = False
    """No compiled report of the rows (see
    :class:`~evtrack.flow.backends.RegistrationBackend`)."""

    def solve(self, group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, g_count: int,
              max_events: int, max_hypotheses: int, pair_budget: int, line_gate: float,
              refine_iters: int, n_ordinals: int) -> GroupSolution:
        """Args: as :func:`evtrack.flow.registration.register_groups` (``pair_budget``: for
        the tensor solve of caps above :data:`MAX_CAP`)."""
        if not fits(max_events, max_hypotheses):
            return TensorRegistration().solve(group, seq, ordinal, flow, g_count, max_events,
                                              max_hypotheses, pair_budget, line_gate,
                                              refine_iters, n_ordinals)
        arr = arrange(group, seq, ordinal, flow, g_count, max_events, max_hypotheses,
                      n_ordinals)
        return _solve_arranged(arr, g_count, max_events, max_hypotheses, line_gate,
                               refine_iters)


def _solve_arranged(arr: Arrangement, g_count: int, max_events: int, max_hypotheses: int,
                    line_gate: float, refine_iters: int) -> GroupSolution:
    """The solve of the capped, arranged candidates by the kernel (:func:`solve_groups`)."""
    c_flow = arr.c_flow
    dev = c_flow.device
    h_count = torch.bincount(arr.h_group, minlength=g_count)
    h_first = torch.cumsum(h_count, 0) - h_count
    ev_ptr = torch.cat([arr.ev_first, torch.full((1,), c_flow.shape[0], dtype=torch.int64,
                                                 device=dev)])
    res = solve_groups(c_flow, ev_ptr, arr.ev_start, arr.ev_per_group, arr.h_idx, h_first,
                       h_count, max_events, max_hypotheses, COST_SCALE, Q_MAX, PARALLEL_EPS,
                       line_gate, IRLS_DELTA, refine_iters, RANK_BITS)
    has = h_count > 0
    nan2 = torch.full((g_count, 2), float("nan"), dtype=torch.float32, device=dev)
    full = torch.where(has[:, None], c_flow[res["chosen"].clamp(0, c_flow.shape[0] - 1)],
                       nan2)
    return GroupSolution(has=has, full=full, best_cost=res["best_cost"],
                         used_events=arr.ev_per_group, inliers=res["inliers"],
                         lines=res["lines"], fit_flow=res["fit_flow"].to(torch.float32),
                         ratio=res["ratio"], major=res["major"].to(torch.float32),
                         normal_speed=res["normal_speed"].to(torch.float32))
