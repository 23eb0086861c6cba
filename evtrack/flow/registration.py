"""RoI registration: one flow per region of interest and time window (the paper's Eq. 3).

For a group (RoI, window) with events ``i = 1..n`` and their candidate sets ``M_i``::

    F = argmin_{F' in M} sum_i min_{c in M_i} |F' - F_ic|

with ``|.|`` the **Euclidean** norm of the 2-D difference (px/s): the sum of norms is the
robust "L1-type" registration cost, invariant to image rotation. ``F`` is a medoid-like
candidate: it is one of the candidate flows.

Evaluated batched over many groups, exactly and deterministically:

* a distance is ``d2 = dx * dx + dy * dy`` in float32 (separate IEEE operations), then
  ``round(sqrt(d2) * COST_SCALE)`` (half to even), capped at ``Q_MAX``, found with exact
  float64 comparisons (:func:`~evtrack.flow.registration_tensor.rounded_distance`; library
  ``sqrt`` need not be correctly rounded, and torch's CPU ``sqrt`` is not), and summed in
  int64, so costs (and thus the arg-min) do not depend on summation order, batch
  composition, device or backend;
* ties go to the hypothesis with the smallest hash (see below);
* caps keep the O(|M|^2) cost bounded: at most ``max_events_per_roi`` events enter the data
  term (those with the smallest hash of their stream index) and at most ``max_hypotheses``
  candidates of those events are tried as ``F'`` (those with the smallest hash of
  (stream index, candidate ordinal)). Hash selection is deterministic, independent of how
  the stream was chunked, and spreads the kept events over the whole window.

Constraint lines, aperture test and refinement. All candidates of one event lie on the
event's constraint line ``n . F = s`` (a local edge with unit normal ``n`` moving at normal
speed ``s`` matches along any displacement ``d`` with ``n . d > 0``, giving ``s d / (n . d)``).
An event gives its line through its candidate nearest to ``F`` (which must lie within
``line_gate * |F|`` of it) and its candidate nearest to ``F`` from a non-parallel
displacement. With the IRLS weights ``w_i`` of the robust
fit below, the 2x2 scatter ``A = sum_i w_i n_i n_i^T`` has eigenvalues ``l_min <= l_max``:

* **aperture**: ``l_min / l_max < aperture_ratio`` (all lines share one normal: an edge). The
  flow is then reported as normal flow ``s_hat * e`` along the dominant normal ``e`` (the
  eigenvector of ``l_max``), ``s_hat = e . b / l_max`` with ``b = sum_i w_i s_i n_i``;
* **refinement** (``refine``): otherwise the flow is the robust intersection of the lines,
  ``argmin_F sum_i |n_i . F - s_i|`` by IRLS started at the Eq. 3 solution. Eq. 3 alone picks
  one candidate, whose direction is quantised to the integer displacements (up to ~9° off for
  radius 3); the intersection removes that quantisation. ``full_flow`` keeps the Eq. 3
  solution.

Consensus. An event *agrees* with ``F`` (is an inlier) when its candidate nearest to ``F`` lies
within ``line_gate * max(|F|, 1)`` of it; ``inliers`` counts them per group. Where the events
were not caused by one rigid motion (illumination changes on a textureless face, flicker,
noise) their candidates are unrelated and few agree with any ``F``: the caller may refuse
such groups (``FlowConfig.min_inlier_fraction``).

Backends (:class:`~evtrack.flow.backends.RegistrationBackend`, chosen by
:func:`~evtrack.flow.backends.resolve`) solve the groups: tensors
(:mod:`evtrack.flow.registration_tensor`), numba on CPU
(:mod:`evtrack.flow.registration_compiled`), Triton on CUDA
(:mod:`evtrack.flow.registration_triton`); :func:`register_groups` turns their solution
into a :class:`Registration`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evtrack.flow.backends import RegistrationBackend
from evtrack.flow.constants import COST_SCALE
from evtrack.flow.registration_tensor import TensorRegistration

__all__ = ["Registration", "register_groups"]


@dataclass
class Registration:
    """Per-group registration output (G groups).

    Attributes:
        flow: (G, 2) float32 px/s; the normal flow where ``normal``; NaN without candidates.
        full_flow: (G, 2) float32 px/s, the arg-min candidate F itself.
        cost: (G,) float32 mean over the kept events of ``min_c |F - F_ic|`` (px/s).
        used_events: (G,) int64 events in the data term (after the cap).
        ratio: (G,) float32 eigenvalue ratio of the aperture test (1 when undefined).
        normal: (G,) bool aperture flag.
        normal_dir: (G, 2) float32 unit normal ``n`` where ``normal``, else NaN.
        lines: (G,) int64 events that gave a constraint line.
        inliers: (G,) int64 events of the data term that agree with ``full_flow`` (their
            candidate nearest to it lies within ``line_gate * max(|F|, 1)``).
        line_flow: (G, 2) float32 px/s, the normal flow of the group's lines along their
            dominant normal (what ``flow`` is where ``normal``); NaN without a line.
        line_normal: (G, 2) float32 that unit normal; NaN without a line.
    """

    flow: Tensor
    full_flow: Tensor
    cost: Tensor
    used_events: Tensor
    ratio: Tensor
    normal: Tensor
    normal_dir: Tensor
    lines: Tensor
    inliers: Tensor
    line_flow: Tensor
    line_normal: Tensor


def register_groups(group: Tensor, seq: Tensor, ordinal: Tensor, flow: Tensor, n_groups: int,
                    max_events: int, max_hypotheses: int, aperture_ratio: float,
                    pair_budget: int, refine: bool = True, line_gate: float = 0.35,
                    refine_iters: int = 5, n_ordinals: int = 1 << 20,
                    backend: RegistrationBackend | None = None,
                    fit_min_lines: int = 2) -> Registration:
    """Solve Eq. 3 for ``n_groups`` groups at once.

    Args:
        group: (M,) int64 group id of each candidate, in ``[0, n_groups)``.
        seq: (M,) int64 stream index of the candidate's event; candidates of one event are
            consecutive and events appear in stream order.
        ordinal: (M,) int64 ordinal of the candidate within its event (distinct per event).
        flow: (M, 2) float32 candidate flows in px/s.
        n_groups: G.
        max_events, max_hypotheses: the caps of the data term and of the tried solutions.
        aperture_ratio: threshold of the aperture test.
        pair_budget: most (hypothesis, candidate) distances evaluated at once (tensor solve).
        refine: replace F by the robust intersection of the events' constraint lines.
        line_gate: an event's line uses its two candidates nearest to F, both within
            ``line_gate * |F|`` of it.
        refine_iters: IRLS iterations of the refinement.
        n_ordinals: a bound on the ordinals, the same for every call on one stream (the
            hypotheses' hash keys are ``seq * n_ordinals + ordinal``: a bound taken from the
            batch would make the selection depend on how the stream was chunked).
        backend: what solves the groups (default: the tensor code,
            :class:`~evtrack.flow.registration_tensor.TensorRegistration`). The compiled
            (:class:`~evtrack.flow.registration_compiled.CompiledRegistration`, CPU) and
            Triton (:class:`~evtrack.flow.registration_triton.TritonRegistration`, CUDA)
            backends give the same ``full_flow``, ``cost``, ``used_events``, ``inliers`` and
            ``lines`` bit for bit; ``flow``, ``ratio`` and ``normal_dir`` to float rounding.
        fit_min_lines: the fewest constraint lines for the aperture test and the refinement
            (:class:`~evtrack.flow.config.FlowConfig`); a single line has ratio 0, so with 1
            its group reports that line's normal flow.

    Returns:
        The :class:`Registration` of every group.
    """
    dev = flow.device
    g_count = n_groups
    nan2 = torch.full((g_count, 2), float("nan"), dtype=torch.float32, device=dev)
    if group.numel() == 0 or g_count == 0:
        return Registration(flow=nan2.clone(), full_flow=nan2.clone(),
                            cost=torch.full((g_count,), float("nan"), device=dev),
                            used_events=torch.zeros(g_count, dtype=torch.int64, device=dev),
                            ratio=torch.ones(g_count, device=dev),
                            normal=torch.zeros(g_count, dtype=torch.bool, device=dev),
                            normal_dir=nan2.clone(),
                            lines=torch.zeros(g_count, dtype=torch.int64, device=dev),
                            inliers=torch.zeros(g_count, dtype=torch.int64, device=dev),
                            line_flow=nan2.clone(), line_normal=nan2.clone())
    if ordinal.numel() and int(ordinal.max()) >= n_ordinals:
        raise ValueError(f"candidate ordinals must be < n_ordinals ({n_ordinals})")
    solver = backend if backend is not None else TensorRegistration()
    sol = solver.solve(group, seq, ordinal, flow, g_count, max_events, max_hypotheses,
                       pair_budget, line_gate, refine_iters, n_ordinals)
    has, full = sol.has, sol.full
    cost = torch.where(has, sol.best_cost.to(torch.float64) / COST_SCALE
                       / sol.used_events.clamp_min(1), torch.nan).to(torch.float32)
    # --- aperture test and refinement
    ratio = sol.ratio
    fitted = has & (sol.lines >= fit_min_lines)
    normal = fitted & (ratio < aperture_ratio)
    n_dir = sol.major
    if refine:
        refined = torch.where(fitted[:, None], sol.fit_flow, full)
        along = sol.normal_speed[:, None] * n_dir  # the lines' own normal speed
    else:
        refined = full
        along = (refined * n_dir).sum(1, keepdim=True) * n_dir  # F projected on the normal
    lined = (has & (sol.lines >= 1))[:, None]
    return Registration(flow=torch.where(normal[:, None], along, refined), full_flow=full,
                        cost=cost, used_events=sol.used_events, ratio=ratio.to(torch.float32),
                        normal=normal, normal_dir=torch.where(normal[:, None], n_dir, nan2),
                        lines=sol.lines, inliers=sol.inliers,
                        line_flow=torch.where(lined, along, nan2),
                        line_normal=torch.where(lined, n_dir, nan2))
