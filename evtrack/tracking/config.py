"""Configuration of :class:`evtrack.Tracker`: one dataclass, loadable from YAML.

``configs/tracker.yaml`` holds the defaults below. :meth:`TrackerConfig.from_dict` and
:meth:`TrackerConfig.from_yaml` read a (partial) mapping: absent fields keep their documented
defaults, unknown fields and values of the wrong type raise a :class:`~evtrack.errors.ConfigError`
that names the file and the field (``flow.window_us``, ``pose_ukf.q_rotation``...).

Units: microseconds for event-clock quantities (``*_us``), milliseconds for latencies and
ages (``*_ms``), pixels, metres, radians, Hz.

Example:
    >>> cfg = TrackerConfig.from_dict({"method": "pose", "pose_rate_hz": 10})
    >>> cfg.method, cfg.pose_rate_hz, cfg.velocity_step_us
    ('pose', 10.0, 1000)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from evtrack.config_values import checked_scalar, unknown_fields
from evtrack.errors import ConfigError
from evtrack.filters.config import (
    PoseTwistUKFConfig,
    PoseUKFConfig,
    VelocityKFConfig,
    config_from_dict,
)
from evtrack.flow.config import FlowConfig
from evtrack.tracking.methods import METHODS, method_names
from evtrack.tracking.pose_flips import HalfTurnResolver

__all__ = [
    "METHODS",
    "DEPTH_SOURCES",
    "FRAME_FLOW_ALGORITHMS",
    "FrameFlowConfig",
    "GEConfig",
    "TrackerConfig",
    "load_tracker_config",
]

#: Where the depth at the RoIs comes from.
DEPTH_SOURCES = ("sensor", "model")
#: Dense optical flow algorithms of the ``frame-flow`` baseline (OpenCV).
FRAME_FLOW_ALGORITHMS = ("dis", "farneback")


@dataclass
class FrameFlowConfig:
    """The ``frame-flow`` baseline (ROFT-like): dense optical flow between consecutive RGB frames.

    Attributes:
        algorithm: ``"dis"`` (OpenCV's DIS optical flow) or ``"farneback"``.
        dis_preset: DIS preset: ``"ultrafast"``, ``"fast"`` or ``"medium"``.
        grid_px: flow samples are taken on a grid of this pitch (pixels, event-camera image)
            inside the predicted object silhouette.
        max_gap_ms: two frames further apart than this (dropped frames) give no flow.
        max_samples: at most this many grid samples per frame pair (evenly thinned).
    """

    algorithm: str = "dis"
    dis_preset: str = "medium"
    grid_px: int = 16
    max_gap_ms: float = 50.0
    max_samples: int = 400

    def __post_init__(self) -> None:
        if self.algorithm not in FRAME_FLOW_ALGORITHMS:
            raise ConfigError(f"field 'algorithm' must be one of {FRAME_FLOW_ALGORITHMS}, "
                              f"got {self.algorithm!r}")
        if self.dis_preset not in ("ultrafast", "fast", "medium"):
            raise ConfigError(f"field 'dis_preset' must be ultrafast, fast or medium, "
                              f"got {self.dis_preset!r}")
        _need_int(self, "grid_px", 1)
        _need_int(self, "max_samples", 1)
        _need_positive(self, "max_gap_ms")


@dataclass
class GEConfig:
    """The ``ge`` baseline: the 1-DoF generative event model (per-event brightness change).

    Each event on the object at pixel ``x`` with polarity ``p``, after the previous event of
    that pixel ``Δt`` earlier, measures one number: the log-brightness change ``p·C`` must
    equal ``−∇L(x) · (J(x) V) Δt`` (brightness constancy), with ``∇L`` the gradient of the
    log intensity of the latest RGB frame, carried to the predicted pose. Linear in ``V``: one
    Kalman row per event, fused with the same decaying-velocity model as the full method.

    Attributes:
        contrast: ``C``, the log-intensity step of one event (the sensor's threshold).
        blur_sigma_px: Gaussian smoothing of the log image before its gradient, pixels.
        min_gradient: events where ``|∇L|`` (1/px) is below this carry no information and are
            skipped.
        max_dt_ms: a pixel's previous event older than this gives no ``Δt`` (the event is
            skipped). The linear model holds within one edge's burst of events; over longer
            gaps the gradient under the pixel changes and such rows pull the speed to zero
            (measured: 50 ms collapses the estimate, 3 ms keeps it).
        residual_std: standard deviation of one event's brightness residual (log units).
        max_events: at most this many events per velocity step enter the update (evenly
            thinned).
        log_eps: the log image is ``log(I + log_eps)`` with ``I`` the luminance in [0, 1].
    """

    contrast: float = 0.2
    blur_sigma_px: float = 1.0
    min_gradient: float = 0.02
    max_dt_ms: float = 3.0
    residual_std: float = 0.3
    max_events: int = 2000
    log_eps: float = 0.01

    def __post_init__(self) -> None:
        for name in ("contrast", "blur_sigma_px", "max_dt_ms", "residual_std", "log_eps"):
            _need_positive(self, name)
        if not (math.isfinite(self.min_gradient) and self.min_gradient >= 0):
            raise ConfigError(f"field 'min_gradient' must be >= 0, got {self.min_gradient}")
        _need_int(self, "max_events", 1)


def _tracker_flow_defaults() -> FlowConfig:
    # One flow window per velocity step: every step's flows are complete at its end.
    # RoIs of 12 px at 640x480: the YCB objects at 0.5-1 m cover a few 32 px RoIs only, and
    # the rotation about the object's own centre is seen through the differences between
    # RoI flows across it. On the benchmark set (four YCB objects, 4 kHz renders, oracle
    # poses, mask margin 32 px) the full method's RMSE on `faster` went 6.22 cm / 21.4 deg
    # (32 px) -> 5.51 / 19.0 (24) -> 4.92 / 16.4 (16) -> 4.89 / 14.9 (12) -> 6.03 / 15.4 (8).
    # The span bound and tolerance of configs/flow_fast.yaml (triplets over at most 40 ms,
    # 5 % tolerance; the flow's generic defaults: no bound, 10 %): on the 4 kHz set they
    # tracked alike (faster 4.78 / 15.1 -> 4.90 / 15.4, regular 2.90 / 6.7 -> 2.74 / 7.4,
    # oracle poses, 17-20 % less time); on the 500 Hz set (the paper's render rate) the
    # generic flow lost the cracker box in two seeds of three (faster 12.8 cm / 28.4 deg ->
    # 7.0 / 19.3; regular the same position, +0.9 deg rotation); with pose networks (the
    # cracker box's own at 5 Hz, 2026-11-26): faster 3.98 / 7.89 -> 3.46 / 6.05 (4 kHz) and
    # 24.4 / 37.3 -> 11.2 / 10.5 (500 Hz), regular 2.05 / 5.06 -> 2.51 / 4.31 and 1.85 /
    # 5.00 -> 2.11 / 4.52; the demo (seeds 0-5) 13.9 cm / 23.5 deg -> 10.1 / 19.5. So they
    # are the tracker's defaults since then; configs/tracker_slow.yaml restores the generic
    # flow for slow motion (edges under ~50 px/s give no triplet within 40 ms).
    # A 12 px RoI of one 1 ms window rarely holds more than a few dozen events: the Eq. 3
    # search over 16 hypotheses from at most 32 events per RoI (generic: 48 from 64) gave the
    # same accuracy (faster 4.94 / 14.89 -> 4.88 / 14.80, regular 3.00 / 6.74 -> 2.94 / 6.62)
    # and cut the flow's time in the tracker by about a fifth (mustard faster 2.6 -> 2.0 s).
    # A RoI window with 2 supporting events is reported (generic: 5): the sparse objects'
    # windows are mostly below 5 (the mustard bottle had 5-6 RoIs a step), and the filter's
    # Laplacian weighting copes with the less certain flows. Full method, oracle poses,
    # regular and faster e_p cm / e_r deg, min_support 5 -> 2 (2026-11-26): 4 kHz set
    # 2.80 / 7.35 and 5.00 / 13.69 -> 2.36 / 6.16 and 4.49 / 11.88; 500 Hz set 2.87 / 8.50
    # and 6.88 / 18.56 -> 2.51 / 6.68 and 7.05 / 17.28; the paper-matched speeds
    # (--preset-speeds paper) at 4 kHz 2.32 / 7.03 and 3.62 / 10.44 -> 2.00 / 5.97 and
    # 2.91 / 9.20, at 500 Hz 2.24 / 7.98 and 4.21 / 11.82 -> 1.99 / 6.29 and 2.78 / 9.62
    # (3 on the 4 kHz sets: between; 1: worse position). With the pose networks of the
    # cracker box and the tomato can at 5 Hz (4 kHz set): 2.75 / 9.45 and 5.19 / 13.87 ->
    # 2.60 / 10.62 and 4.86 / 13.81 (the regular rotation 1.2 deg worse).
    # Only the last event of each pixel and polarity is tried as e_j and e_i (history 1;
    # generic: 2), 2026-12-01, shipped networks, `evaluate --methods full`, e_p cm / e_r deg,
    # paper-matched regular, faster / default presets' regular, faster: 1.17 / 6.66, 2.48 /
    # 10.75, 1.67 / 6.84, 4.29 / 11.73 -> 1.10 / 7.00, 2.48 / 10.68, 1.70 / 6.93, 4.07 /
    # 11.70; the demo (seeds 0-2, full) 2.69 / 7.89, 3.29 / 10.56, 10.27 / 18.43 -> 2.16 /
    # 8.68, 3.18 / 10.72, 10.53 / 17.89, its `velocity` better on all three; the flow 14-25 %
    # faster (one candidate pair per displacement instead of four), the tracker 8-20 %
    # (benchmarks/bench_tracker_options.py, median of 3, two runs on a noisy VM: the default
    # presets' cracker box `faster` 1.99 -> 1.76 and 2.12 -> 1.93 x real time, the tomato
    # can 0.99 -> 0.79 and 1.26 -> 1.17). The older events of a pixel mostly
    # add triplets of an earlier edge passage, whose slower, spurious flows the registration
    # then has to outvote.
    return FlowConfig(window_us=1000, roi_size=12, max_hypotheses=16, max_events_per_roi=32,
                      max_span_us=40_000, tolerance_rel=0.05, min_support=2, history=1)


def _pose_ukf_defaults() -> PoseUKFConfig:
    # The twist from event flow is biased on weakly observable directions (rotation about the
    # object's own centre, motion in depth): over a pose period the pose drifts by centimetres
    # and tens of degrees. The process noise must cover that drift, or the gate rejects good
    # poses (measured on simulated fast sequences: q_translation 1e-3 rejected 1 to 2 of 5 exact
    # poses per second; 1e-2 m²/s and 0.3 rad²/s reject none).
    # When the twist has carried the pose far off, the gate rejects the good poses that would
    # bring it back: the filter re-initialises on the third rejected pose in a row (0.6 s at
    # 5 Hz) instead of the filter's default sixth. Demo sequences (coded box, network poses,
    # seeds 0-5): mean 17.5 cm / 27.6 deg -> 15.9 / 25.2 (seed 3: 42.6 / 61.7 -> 32.8 / 47.4;
    # the other seeds unchanged). Taking the second (reinit_after 2: 14.0 / 22.6) would accept
    # two random outliers in a row, which tests/tracking/test_robustness.py rejects; the
    # tracker's reinit_on_agreement takes the second only when the two agree with each other
    # (with RANSAC decoding, full method: 15.6 / 25.7 -> 13.9 / 23.1; seed 3 32.6 -> 25.7 cm,
    # seed 2 26.2 -> 22.4 cm, the others unchanged).
    # The velocity bias (not in the paper): on fast motion the event twist reads the object
    # approaching faster than it does (-0.05 to -0.09 m/s along the optical axis on the default
    # presets' `faster` sequences, ~0 on `regular`), so between two poses, and over the network's
    # 200 ms latency, the track falls behind in depth. The filter learns that bias, scaled by the
    # object's speed (nothing moves at rest), from the pose updates' innovations. evaluate --methods
    # full, shipped networks, the four columns (paper-matched regular, faster; default presets
    # regular, faster), without -> with (2026-12-01, step groups of 10 ms; with groups of 40 ms,
    # 2026-12-02, the default presets' `faster` 4.15 / 11.57 -> 3.93 / 11.59): 1.10 / 7.00, 2.48 /
    # 10.68, 1.70 / 6.93, 4.07 / 11.70 -> 1.10 / 7.00, 2.48 / 10.68, 1.66 / 6.93, 3.89 / 11.67;
    # default presets with (q, init) (0.01, 0.1) 1.64, 3.95 cm, (0.03, 0.1) 1.60, 3.95. It cannot
    # learn more than the networks' own range errors allow (the known mean bias would give 3.44 cm
    # on the default `faster`).
    return PoseUKFConfig(q_translation=0.01, q_rotation=0.3, reinit_after=3,
                         velocity_bias=True, q_velocity_bias=0.01, init_std_velocity_bias=0.05)


def _pose_only_defaults() -> PoseUKFConfig:
    # Without a twist the pose is a random walk between 5 Hz poses: its process noise must
    # cover the object's motion over a pose period or the gate rejects every pose.
    return PoseUKFConfig(q_translation=0.5, q_rotation=5.0)


def _frame_flow_kf_defaults() -> VelocityKFConfig:
    # One twist per frame pair from dense (full, not normal) flow: no decay inside the pair
    # and no process noise (the filter starts afresh on each pair, so no pivot either).
    return VelocityKFConfig(normal_flow=False, assume_normal=False, flow_std=20.0,
                            init_std_linear=2.0, init_std_angular=6.0, object_centred=False)


def _pose_twist_defaults() -> PoseTwistUKFConfig:
    # The pose process noise of the full method's UKF (_pose_ukf_defaults): the dense-flow twist
    # drifts as the event twist does, and a tighter noise made the gate reject good poses
    # (oracle poses, the four YCB `faster` sequences at 4 kHz: 28.4 cm / 39.7 deg with the
    # filter's defaults, 21.8 cm / 38.5 deg with these; 18.4 cm / 33.7 deg once the frame
    # pairs before a late first pose were measured too).
    return PoseTwistUKFConfig(q_translation=0.01, q_rotation=0.3)


_REMOVED_FIELDS = {
    "depth_range_scale": "the range is measured on surface points of the mesh in 4-px image "
                         "cells, not on a render (2026-11-28); delete the field",
}
"""Fields of earlier versions, with what to do instead (an error that says so, not a bare
"unknown field")."""


@dataclass
class TrackerConfig:
    """Everything :class:`evtrack.Tracker` needs besides the cameras, the object and the sources.

    Attributes:
        method: ``"full"`` (the paper: event flow -> velocity KF -> pose UKF with poses),
            ``"velocity"`` (the twist integrated after the first pose only), ``"pose"`` (UKF with
            poses only), ``"frame-flow"`` (ROFT-like: dense RGB flow -> twist measurements of a
            constant-velocity pose UKF), ``"ge"`` (1-DoF generative event model).
        device: torch device of the flow and the filters (``"cpu"``, ``"cuda"``).
        torch_threads: CPU threads torch (and the flow's compiled kernels, which follow
            torch's count) use during :meth:`Tracker.track`, restored after; never more than
            the cores this process may use; 0 leaves torch's setting. Two by default: on 2
            cores the flow runs a third faster than on one (``benchmarks/bench_tracker.py
            --threads 1 2``: real-time factor 3.0 against 3.9) and the tiny per-step filter
            ops cost the same. Threads beyond the free cores are far slower (2 threads on 2
            busy cores made a run 20x slower than 1), so ``evtrack evaluate --jobs N`` gives
            each job its share of the cores. Streaming callers set ``torch.set_num_threads``
            themselves.
        blas_threads: numpy's BLAS threads while the tracker works (``track`` and the
            streaming calls), restored after each call; 0 leaves the library's setting. One by
            default: the tracker's numpy products are small, and OpenBLAS's idle workers spin
            after each larger one and take a core from the flow (see
            :mod:`evtrack.runtime.blas_threads`, also for trackers running in several threads at
            once:
            give them 0 and limit BLAS around them).
        velocity_step_us: the velocity filter runs once per step (µs); the tracker outputs a
            pose and a twist at the end of every step (1 kHz by default). Steps are aligned on
            absolute time (multiples of the step).
        flow_batch_steps: the event flow runs once per this many velocity steps (one call on
            their events, masked with the convex hull of the silhouette predicted at the first
            step and the one predicted at the last step's end with the current twist). The
            filters still step once per step and take the pose, its silhouette and the
            velocity filter's pivot afresh every 10 steps, as groups of 10 did. Groups of steps
            are aligned on absolute time, so results do not depend on how the events are
            chunked. The outputs of a group are available at its end: a delay of up to
            ``flow_batch_steps`` steps in live use (:meth:`Tracker.pose` extrapolates with the
            current twist meanwhile). 40 by default: each flow call has a fixed cost (a few ms
            of Python, small kernels, thread wake-ups), and 40 instead of 10 took about a third
            off the tracking time of three of the four `faster` YCB sequences on 2 cores of an
            AMD EPYC, 2026-12-02 (`benchmarks/bench_tracker_options.py`; ``docs/results.md``,
            "Step groups of 40 ms and of 10 ms"), with the benchmark errors of groups of 10 to
            every digit except the default presets' cracker box `faster` (2.74 cm / 5.69 deg
            against 2.55 / 6.01) and the demo's seeds 0-5 at 6.12 cm / 12.27 deg against
            5.94 / 12.55. For live use where the delay matters, 10 costs that time back.
        mask_margin_px: events are kept when they lie within this distance (pixels) of the
            object's predicted silhouette (the convex hull of the projected mesh). It must
            cover the predicted pose's error, or the events of one side are lost and the
            flow is biased: with oracle poses (1 cm, 0.03 rad noise) on the `faster`
            benchmark set, 8 px gave a rotation RMSE twice that of 32 px (cracker box: 10.3
            vs 5.4 deg); 48 px gave the same as 32. Scale it with the image width.
        burst_rate_hz: a velocity step whose events outside the (grown) silhouette exceed this
            rate per pixel of the image outside it (events per pixel per second) is an event
            burst (flicker, a sensor glitch): its events are not used and the velocity filter
            only predicts; 0 disables. The object's own events cannot reach it (at 640x480 a
            fast object gives ~6 events per pixel per second over the whole image); sensor
            background activity is 0.1 to a few Hz per pixel. Assumes a static camera: a
            moving camera's textured background can reach it by itself (set 0 then).
        max_events_per_step: at most this many events per velocity step (on average over a
            step group) enter the flow (or the GE model); above it they are thinned by whole
            cells of 2 x 2 RoIs, deterministically, and counted (see
            :mod:`evtrack.tracking.tracker`),
            which bounds the work per step; 0: no cap. Thinning costs accuracy: on the
            cracker box `faster` (8.6 M events/s) 4000 gave 9.2 cm / 13.8 deg against 4.35 /
            6.5 unthinned, in 0.4x the time (real-time factor 10.1 -> 4.0). The default is
            ~5x the peak rate of the fast 640x480 simulated sequences (3.8k events per ms on
            the whole sensor).
        search_per_roi_window: the flow searches at most about this many events of one RoI
            window for candidates, a sample by the hash that also picks the registration's
            data term (:func:`evtrack.flow.sampling.sampled_search`); all events still enter
            the search's history, so the searched events' triplets are those of the whole
            stream, and a window whose sample holds ``flow.max_events_per_roi``
            candidate-bearing events registers the same flow as unsampled. 0: search all.
        max_searched_per_step: at most this many of those events per velocity step (on
            average over a step group) are searched, by whole RoIs visited in a fixed hash
            order and taken while they fit (:func:`~evtrack.flow.sampling.sampled_search`'s
            ``budget``); the other RoIs' events still enter the history, so a taken RoI's flow
            is the one it would have without the budget and only the left-out RoIs give no
            flow. It bounds the flow's search and registration, its dominant costs, whatever
            the event rate. 0: no bound. On the four YCB objects' benchmark set (4 kHz, oracle
            poses) only the cracker box `faster` (8.6 M events/s, ~5k sampled events per ms)
            reaches 2500 after its first pose: 3.90 cm / 4.98 deg without a budget, 3.90 /
            4.74 with 2500 (3000: 4.16 / 4.90; 2000: 4.13 / 5.23; 1500: 4.46 / 4.78; 1000:
            5.24 / 5.84); the tomato can `regular`'s first 200 ms (all events, before the
            first pose) move a little (5.53 -> 4.91 deg); the other sequences are unchanged.
        realtime_load: keep up with a live stream: the processing of the step groups (the
            flow, the filters and the frames taken meanwhile) beyond this share of their stream
            time accumulates as a backlog; while the backlog exceeds 5 groups and the load
            (smoothed over ~10 groups) stays above this share, the search budget per step and
            the events per step (thinned by cells, as by ``max_events_per_step``) are cut
            together for the next groups, down to ``min_searched_per_step`` and
            ``min_events_per_step``; while there is no backlog both are raised again towards
            ``max_searched_per_step`` and ``max_events_per_step``
            (:meth:`~evtrack.tracking.tracker.Tracker._adapt_budgets`). The budgets then follow the
            machine's speed and load, and so do the results: 0 (the default) keeps them
            deterministic. Needs ``max_searched_per_step > 0``. The work no budget bounds
            (reading and masking every event, the filters and the pose fusions: ~0.7-0.8 of
            real time on 2 cores of a slow AMD EPYC with few events, 2026-12-02) stays.
            Shedding events costs accuracy: see ``docs/results.md``, "Live use:
            realtime_load".
        min_searched_per_step: the lowest search budget ``realtime_load`` goes to.
        min_events_per_step: the lowest event budget ``realtime_load`` goes to; 0: it never
            sheds events (only the search budget adapts). The floors bound the accuracy lost:
            on the cracker box `faster` (its network at 5 Hz, 2 cores of a slow AMD EPYC,
            2026-12-02) 1000 and 2000 gave 3.9-4.2 cm / 9.4-10.5 deg at 1.25-1.34 of real time
            (2.74 / 5.69 at 1.75-2.4 without ``realtime_load``; the search budget alone down to
            250: 5.4-5.7 / 10-12.3 at 1.34-1.64; 250 and 500: 10.6 / 17-19 at 1.07-1.12).
        lost_after_ms: the object counts as lost when its predicted silhouette has stayed
            outside the image (less than ``min_visible_fraction`` of its hull area inside) for
            this long; the pose filter then waits for the next pose to re-initialise.
        min_visible_fraction: see ``lost_after_ms``.
        lost_after_misses: the object also counts as lost when this many pose-source calls in
            a row found nothing (or only detections below ``pose_min_confidence``), counted when
            each result would have been available; 0 disables. A detector finds nothing once
            the object has left the image, while the prediction, without events to follow,
            can stop short inside it. With the default 3 at 5 Hz: 0.6 s without a detection.
        depth_source: ``"sensor"`` (the RGB-D depth frames, carried into the event camera) or
            ``"model"`` (depth rendered from the mesh at the predicted pose).
        depth_patch_px: the depth of a RoI is the median of the valid depths within this
            radius (pixels, square patch) of its centre that lie inside the predicted silhouette.
        depth_stride_px: pitch of the depth samples in that patch (pixels).
        max_depth_age_ms: a sensor depth frame older than this is not used; RoIs then take the
            fallback depth (the predicted depth of the object's origin) and are counted.
        model_depth_interval_us: the ``model`` depth map is re-rendered at most this often.
        model_depth_scale: the ``model`` depth map is rendered at this fraction of the event
            camera's resolution.
        depth_range: fuse the object's range along its viewing ray, measured on every sensor
            depth frame against the mesh's surface at the predicted pose
            (:mod:`evtrack.tracking.depth_range`), into the pose filter: the depth the event flow
            sees
            worst. Off by default (the paper's method uses depth only for the flow's
            interaction matrix); needs ``depth_source: sensor`` and the object's mesh (with
            faces). Not used by ``velocity``, which takes poses only to initialise.
        depth_range_std_m: the floor of a range measurement's standard deviation (m).
        depth_icp: align the object's mesh with sensor depth frames (point-to-plane ICP,
            :class:`~evtrack.models.DepthRefiner`) from the filter's pose at each frame's time
            and fuse the aligned pose (:meth:`~evtrack.filters.PoseUKF.update_aligned`) with
            the fit's own covariance: what the depth cannot see (a can turning about its
            axis, sliding within a face seen head-on) stays with the events and the pose
            source. The event flow sees an object's turn about an axis across the image
            barely apart from a shift; the depth sees it. Off by default (not in the paper);
            needs ``depth_source: sensor`` and the object's mesh. Not used by ``velocity``.
        depth_icp_rate_hz: at most this many depth frames per second are aligned (each costs
            13-17 ms of one CPU core with the defaults below, for a YCB object at 640x480:
            ``track`` took 3.6-3.8 s for the 2 s of the mustard bottle ``faster`` instead of
            2.5-2.8, 10.6-11.0 s for the cracker box instead of 10.1-10.5, on 2 cores).
        depth_icp_points: mesh surface samples of the fit (about half face the camera).
        depth_icp_scene_points: most depth pixels around the object used by the fit.
        depth_icp_std_m, depth_icp_std_deg: floors added to the fit's translation and rotation
            standard deviations (m, degrees): the fit's own covariance assumes independent
            depth errors, which a real sensor's (ripple, flying pixels, a scale bias) are not.
        pose_rate_hz: the pose source runs on RGB frames at this rate (the paper: 5 Hz).
        pose_latency_ms: a pose computed from the frame at ``t`` becomes available to the
            filter at ``t + latency`` (simulated offline, as in the paper; the filter rolls back
            to ``t`` to fuse it). Default: one pose period (a network just fast enough for its
            rate).
        pose_min_confidence: detections below this confidence are ignored (they count as
            misses, see ``lost_after_misses``).
        pose_async: in :meth:`~evtrack.tracking.tracker.Tracker.track` (offline), run the pose
        source
            in a worker thread of the tracker (one, so calls keep the frames' order) and take
            its result when it becomes available to the filter (``pose_latency_ms`` after the
            frame): the same trajectory and statistics as calling it at the frame (the tests
            compare both), while the network's time and the RGB frame's decoding overlap the
            event tracking (a pose-network call on a CPU takes 20-40 ms; the tracking runs
            mostly on one core). The pose source is then called from that thread, within
            ``track``'s BLAS limit where the library's limit is process-wide (OpenBLAS, as in
            numpy's wheels); its exception surfaces from ``track``. A result due at once
            (``pose_latency_ms`` 0) is computed at once. The streaming calls always run the
            pose source in the caller's thread: a live application runs its network where it
            likes and hands the poses to :meth:`~evtrack.tracking.tracker.Tracker.push_pose`.
        pose_prior: while the track holds, hand the pose source the tracker's pose at the
            frame's time (``prior=``, to sources whose ``accepts_prior`` is true:
            :class:`~evtrack.tracking.pose_sources.NetworkPoseSource`), which looks for the object
            there first: the network then runs once, on a crop around that pose, instead of
            on the whole image and then on a crop
            (:meth:`~evtrack.models.PoseEstimator.estimate_near`; the whole image again when
            the crop does not find the object near its centre). Before the first pose and
            after a loss, no prior: the whole image.
        reinit_on_agreement: when a pose is rejected by the pose filter's gate right after
            another rejected pose and the two agree with each other (the second within
            ``reinit_agree_m + reinit_agree_m_per_s * dt`` metres and ``reinit_agree_deg +
            reinit_agree_deg_per_s * dt`` degrees of the first, ``dt`` seconds later), the
            filter re-initialises on the second: the filter has drifted off, the poses have
            not. Random outliers rarely agree with each other, so they stay rejected (the
            filter's ``reinit_after`` still re-initialises after that many rejections in a
            row, agreeing or not).
        reinit_agree_m, reinit_agree_m_per_s, reinit_agree_deg, reinit_agree_deg_per_s: see
            ``reinit_on_agreement``.
        pose_depth_min_share: a pose (from the pose source or :meth:`Tracker.push_pose`) is
            dropped (counted in ``TrackerStats.poses_implausible``) when, of the valid
            sensor-depth pixels inside its silhouette (sampled every 4 px, on the depth frame
            nearest the pose's time: the sensor maps of the last ``history_ms`` are kept for
            poses that arrive late), fewer
            than this share lie in the object's depth range at that pose widened by
            ``pose_depth_tolerance_m``: the depth shows that the object is not where the pose
            puts it. A network can only see what is visible, so a right pose has most of its
            silhouette at its own depth; occluders count against it, hence a share below 1.
            It stops gross network errors (e.g. a bottle seen from below, turned half a turn
            and pushed a metre back: shares 0-0.33, right poses 0.6-1.0 on the benchmark)
            from re-initialising the filter. 0: off; no check without a sensor depth frame
            within ``max_depth_age_ms`` of the pose or with fewer than 16 valid pixels.
        pose_depth_tolerance_m: see ``pose_depth_min_share``.
        pose_depth_align: before that check, move each pose along its viewing ray until the
            object's surface at the pose lies on its frame's sensor depth
            (:class:`~evtrack.tracking.pose_alignment.PoseRayAligner`; rotation and the position
            across
            the ray kept). An RGB network errs mostly in range: the mustard bottle's poses on
            the paper-matched `faster` sequence were 11-14 cm off along the ray and under 1 cm
            across it, 0.2-0.7 cm after the alignment. Needs the object's mesh with faces and
            a sensor depth frame (as the check); a pose is left as it is when too few image
            cells see both its surface and a valid depth, when they disagree (the pose is off
            across the ray or turned), or when the move would exceed
            ``pose_depth_align_max_m``. Not in the paper (its pose network uses RGB only).
        pose_depth_align_max_m: the largest move of ``pose_depth_align``, metres: a pose
            farther off is a gross error for the check to drop, not to move onto whatever lies
            behind it.
        pose_alternatives: where a pose fails that check, try the other poses its detector
            found in the same image
            (:attr:`~evtrack.tracking.pose_sources.PoseMeasurement.alternatives`,
            e.g. the first pass's detection where the network's crop pass replaced it, or the
            strongest peaks' fit where the corner search's was kept), most confident first,
            each aligned and checked the same way; the first that passes is used in its place
            (counted in ``TrackerStats.poses_from_alternatives``). The depth, not the
            confidence, picks among them: on the mustard bottle's end-on frames the kept pose
            had confidence 0.00 and lay 0.6 m off while the first pass's (0.15) lay at the right
            range. Needs the same as the check; off or without alternatives, the pose is just
            dropped. Not in the paper.
        pose_alternatives_min_confidence: alternatives less confident than this (or than
            ``pose_min_confidence``) are not tried. A corner-identity confusion can give a pose
            turned half a turn at the right range, which the depth confirms: on the benchmark
            the alternatives the depth confirmed had confidences 0.64-0.85 and lay 2-9° off,
            except one of 0.15 turned 176°, which the ``pose`` baseline (no events to hold its
            filter) then fused (mustard bottle, paper-matched `faster`: 84° instead of 29°).
        pose_half_turn_axes: the object-frame axes (a string of ``x``, ``y``, ``z``; ``""``:
            none) whose half turns the pose network may confuse where it sees the object along
            them: each pose seen within ``pose_half_turn_max_view_deg`` of one of these axes is
            replaced by its half turn about that axis (through the cuboid's centre) when that
            lies nearer the filter's pose at the pose's time, in rotation
            (:class:`~evtrack.tracking.pose_flips.HalfTurnResolver`; counted in
            ``TrackerStats.poses_half_turned``). A cuboid-keypoint network's corner swaps give
            exactly these poses, at the right range, and seen along the axis their silhouettes
            agree, so the depth check cannot drop them (the mustard bottle seen from below:
            ``y``). Applied after the depth check, once the filter is initialised; the pose's
            covariance is kept. Not in the paper.
        pose_half_turn_max_view_deg: see ``pose_half_turn_axes``, degrees in [0, 90].
        pose_half_turn_reinit_after: the filter re-initialises on the pose as it is (not
            turned) when this many fused poses in a row needed the turn: a network that turns
            its poses now and then does not turn several in a row, a track that started on a
            turned pose disagrees with every right one (0: never; the turned track is then
            corrected only once the views leave the axes' cones).
        history_ms: how far back the pose filter keeps its past states for late poses; a pose
            older than that is dropped and counted.
        velocity_before_pose: before the first pose (and after losing the object) run the
            flow and the velocity filter on all events, with the sensor depth's patch medians,
            so that the first pose, which arrives ``pose_latency_ms`` late, is carried to the
            present by the measured motion (``full`` and ``velocity``). Model depth needs a
            pose: with ``depth_source: model`` the flow runs but the velocity filter only
            predicts, and the steps wait for ``remeasure_on_pose``.
        remeasure_on_pose: with ``velocity_before_pose``, keep those steps' RoI flows and depth
            frames (model depth: rendered at the timeline's poses then; on the benchmark set, 4
            kHz, oracle poses, this took ``depth_source: model`` from 11.82 cm / 25.15 deg to
            6.44 / 16.63 on `faster` and from 3.04 / 8.22 to 2.70 / 6.49 on `regular`,
            2026-11-27: without it the first pose, 200 ms old, is held still and the track
            starts far off), and once the late pose has started the track, measure the steps
            since that pose again at the poses the filter then has (RoIs inside the silhouette,
            depths in its range, the object's centre as pivot) and carry the pose to the present
            with these twists. Without a pose, neither the object's depth range nor its centre
            is known: stale depth frames put many RoIs on the background and the motion about
            the camera's origin confounds translation with rotation. Measured again at a wrong
            pose, though, the steps lose their RoIs and take depths out of the object's range,
            which carries the wrong pose further off: see ``remeasure_min_inside``.
        remeasure_min_inside: the steps are measured again only when at least this fraction
            of the RoI flows (of at least 5 supporting events) of the 50 ms after the pose
            lie in the silhouette (with
            ``mask_margin_px``) at the timeline's pose of their step, else they keep their
            twists (counted in ``TrackerStats.remeasures_skipped``). Measured: 0.999-1.0 for
            oracle poses (1 cm, 1.7° per axis) on the eight YCB sequences and for the demo's
            network on seeds 0 and 2-5; 0.94 for its first pose of seed 1, 9.5 cm and 36° off.
        use_flow_normal_flags: pass the flow's per-RoI aperture flags to the velocity filter
            (normal-only rows where the flow saw one edge direction). Off, every RoI gets
            ``velocity_kf.assume_normal`` (the paper treats every flow as a normal flow).
        flow: the event optical flow (:class:`~evtrack.flow.FlowConfig`); ``velocity_step_us``
            must be a multiple of ``flow.window_us``. The tracker's defaults differ from the
            flow's: 1 ms windows, 12 px RoIs, Eq. 3 over 16 hypotheses from 32 events,
            triplets over at most 40 ms with a 5 % tolerance (fast objects; for slow motion
            ``configs/tracker_slow.yaml``) from the last event of each pixel and polarity.
            The measurements are in ``_tracker_flow_defaults``.
        velocity_kf: the velocity Kalman filter (ablations: ``normal_flow``, ``weighting``).
        pose_ukf: the pose UKF of ``full``, ``velocity`` and ``ge``.
        pose_only_ukf: the pose UKF of the ``pose`` baseline (random-walk process noise).
        pose_twist_ukf: the constant-velocity pose UKF of ``frame-flow``.
        frame_flow: dense RGB flow settings of ``frame-flow``.
        frame_flow_kf: the velocity filter that turns one frame pair's flows into a twist
            measurement (``frame-flow``).
        ge: the generative event model of ``ge``.
    """

    method: str = "full"
    device: str = "cpu"
    torch_threads: int = 2
    blas_threads: int = 1
    velocity_step_us: int = 1000
    flow_batch_steps: int = 40
    mask_margin_px: float = 32.0
    burst_rate_hz: float = 100.0
    max_events_per_step: int = 20_000
    search_per_roi_window: int = 64
    max_searched_per_step: int = 2500
    realtime_load: float = 0.0
    min_searched_per_step: int = 1000
    min_events_per_step: int = 2000
    lost_after_ms: float = 100.0
    min_visible_fraction: float = 0.05
    lost_after_misses: int = 3
    depth_source: str = "sensor"
    depth_patch_px: int = 16
    depth_stride_px: int = 4
    max_depth_age_ms: float = 100.0
    model_depth_interval_us: int = 5000
    model_depth_scale: float = 0.5
    depth_range: bool = False
    depth_range_std_m: float = 0.005
    depth_icp: bool = False
    depth_icp_rate_hz: float = 30.0
    depth_icp_points: int = 1000
    depth_icp_scene_points: int = 3000
    depth_icp_std_m: float = 0.002
    depth_icp_std_deg: float = 1.0
    pose_rate_hz: float = 5.0
    pose_latency_ms: float = 200.0
    pose_min_confidence: float = 0.0
    pose_async: bool = True
    pose_prior: bool = False
    reinit_on_agreement: bool = True
    reinit_agree_m: float = 0.05
    reinit_agree_m_per_s: float = 1.0
    reinit_agree_deg: float = 10.0
    reinit_agree_deg_per_s: float = 180.0
    pose_depth_min_share: float = 0.5
    pose_depth_tolerance_m: float = 0.06
    pose_depth_align: bool = True
    pose_depth_align_max_m: float = 0.2
    pose_alternatives: bool = True
    pose_alternatives_min_confidence: float = 0.3
    pose_half_turn_axes: str = ""
    pose_half_turn_max_view_deg: float = 30.0
    pose_half_turn_reinit_after: int = 2
    history_ms: float = 1000.0
    velocity_before_pose: bool = True
    remeasure_on_pose: bool = True
    remeasure_min_inside: float = 0.98
    use_flow_normal_flags: bool = True
    flow: FlowConfig = field(default_factory=_tracker_flow_defaults)
    velocity_kf: VelocityKFConfig = field(default_factory=VelocityKFConfig)
    pose_ukf: PoseUKFConfig = field(default_factory=_pose_ukf_defaults)
    pose_only_ukf: PoseUKFConfig = field(default_factory=_pose_only_defaults)
    pose_twist_ukf: PoseTwistUKFConfig = field(default_factory=_pose_twist_defaults)
    frame_flow: FrameFlowConfig = field(default_factory=FrameFlowConfig)
    frame_flow_kf: VelocityKFConfig = field(default_factory=_frame_flow_kf_defaults)
    ge: GEConfig = field(default_factory=GEConfig)

    def __post_init__(self) -> None:
        self._check_types()
        if self.method not in method_names():
            raise ConfigError(f"tracker config field 'method' must be one of {method_names()}, "
                              f"got {self.method!r}")
        if self.depth_source not in DEPTH_SOURCES:
            raise ConfigError(f"tracker config field 'depth_source' must be one of "
                              f"{DEPTH_SOURCES}, got {self.depth_source!r}")
        for name in ("torch_threads", "blas_threads", "velocity_step_us", "flow_batch_steps",
                     "depth_patch_px", "depth_stride_px", "model_depth_interval_us",
                     "lost_after_misses", "max_events_per_step", "search_per_roi_window",
                     "max_searched_per_step", "min_searched_per_step", "min_events_per_step",
                     "pose_half_turn_reinit_after"):
            _need_int(self, name, 0 if name in ("depth_patch_px", "torch_threads", "blas_threads",
                                                "lost_after_misses", "max_events_per_step",
                                                "search_per_roi_window", "max_searched_per_step",
                                                "min_events_per_step",
                                                "pose_half_turn_reinit_after")
                      else 1)
        for name in ("mask_margin_px", "lost_after_ms", "max_depth_age_ms", "pose_latency_ms",
                     "pose_min_confidence", "burst_rate_hz", "reinit_agree_m",
                     "reinit_agree_m_per_s", "reinit_agree_deg", "reinit_agree_deg_per_s",
                     "pose_depth_tolerance_m", "realtime_load",
                     "pose_alternatives_min_confidence"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"tracker config field {name!r} must be finite and >= 0, "
                                  f"got {value!r}")
        for name in ("pose_rate_hz", "history_ms", "pose_depth_align_max_m"):
            _need_positive(self, name)
        for name in ("model_depth_scale",):
            value = getattr(self, name)
            if not 0 < value <= 1:
                raise ConfigError(f"tracker config field {name!r} must be in (0, 1], "
                                  f"got {value}")
        for name in ("depth_range_std_m", "depth_icp_rate_hz", "depth_icp_points",
                     "depth_icp_scene_points", "depth_icp_std_m", "depth_icp_std_deg"):
            _need_positive(self, name)
        for name in ("depth_range", "depth_icp"):
            if getattr(self, name) and self.depth_source != "sensor":
                raise ConfigError(f"tracker config field {name!r} needs depth_source 'sensor' "
                                  f"(got {self.depth_source!r}): it measures on the RGB-D "
                                  "depth frames")
        if self.realtime_load and not self.max_searched_per_step:
            raise ConfigError("tracker config field 'realtime_load' needs a search budget to "
                              "adapt: set 'max_searched_per_step' > 0 (the highest budget)")
        if self.realtime_load and self.min_searched_per_step > self.max_searched_per_step:
            raise ConfigError(f"tracker config field 'min_searched_per_step' "
                              f"({self.min_searched_per_step}) must not exceed "
                              f"'max_searched_per_step' ({self.max_searched_per_step})")
        if self.realtime_load and self.max_events_per_step \
                and self.min_events_per_step > self.max_events_per_step:
            raise ConfigError(f"tracker config field 'min_events_per_step' "
                              f"({self.min_events_per_step}) must not exceed "
                              f"'max_events_per_step' ({self.max_events_per_step}); 0 keeps "
                              "realtime_load from shedding events")
        if not isinstance(self.pose_half_turn_axes, str):
            raise ConfigError(f"tracker config field 'pose_half_turn_axes' must be a string of "
                              f"'xyz' letters, got {self.pose_half_turn_axes!r}")
        try:  # the resolver's own checks of both fields
            HalfTurnResolver(self.pose_half_turn_axes, np.zeros(3),
                             self.pose_half_turn_max_view_deg)
        except ValueError as exc:
            raise ConfigError(f"tracker config fields 'pose_half_turn_axes' / "
                              f"'pose_half_turn_max_view_deg': {exc}") from exc
        for name in ("min_visible_fraction", "remeasure_min_inside", "pose_depth_min_share"):
            value = getattr(self, name)
            if not 0 <= value <= 1:
                raise ConfigError(f"tracker config field {name!r} must be in [0, 1], "
                                  f"got {value}")
        if self.velocity_step_us % self.flow.window_us:
            raise ConfigError(
                f"tracker config: velocity_step_us ({self.velocity_step_us}) must be a multiple "
                f"of flow.window_us ({self.flow.window_us}) so that every step's flows are "
                "complete at its end")
        if self.pose_rate_hz > 1e6 / self.velocity_step_us:
            raise ConfigError(
                f"tracker config field 'pose_rate_hz' ({self.pose_rate_hz:g}) must not exceed "
                f"one pose per velocity step ({1e6 / self.velocity_step_us:g} Hz)")
        if self.history_ms < self.pose_latency_ms + 1e3 / self.pose_rate_hz:
            raise ConfigError(
                f"tracker config: history_ms ({self.history_ms}) must cover pose_latency_ms "
                f"({self.pose_latency_ms}) plus one pose period ({1e3 / self.pose_rate_hz:g} ms)")

    def _check_types(self) -> None:
        """Each field's type, as :meth:`from_dict` checks it, for the direct constructor too
        (``TrackerConfig(depth_icp="false")`` must not turn ICP on); a section given as a
        mapping (``velocity_kf={"flow_std": 20.0}``) becomes its config, the other fields at
        their defaults."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            default = (f.default if f.default is not dataclasses.MISSING
                       else f.default_factory())  # type: ignore[misc]
            if dataclasses.is_dataclass(default):
                if isinstance(value, Mapping):
                    where = f"tracker config: {f.name}"
                    value = (_flow_from(value, default, where) if f.name == "flow"
                             else _section_from(type(default), value, default, where))
                elif not isinstance(value, type(default)):
                    raise ConfigError(
                        f"tracker config field {f.name!r} must be a {type(default).__name__} "
                        f"or a mapping of its fields, got {type(value).__name__}")
            else:
                value = checked_scalar(f.name, value, default, "tracker config")
            setattr(self, f.name, value)

    # ------------------------------------------------------------------ derived values
    @property
    def pose_period_us(self) -> int:
        """The pose source's period in µs."""
        return int(round(1e6 / self.pose_rate_hz))

    @property
    def pose_latency_us(self) -> int:
        return int(round(self.pose_latency_ms * 1e3))

    # ------------------------------------------------------------------ loading
    def replace(self, **changes: Any) -> TrackerConfig:
        """A copy with some top-level fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None, source: str = "tracker config",
                  base: TrackerConfig | None = None) -> TrackerConfig:
        """Build from a (partial) mapping; absent fields keep the defaults (or ``base``'s).

        Raises:
            ConfigError: an unknown field, a value of the wrong type or out of range, naming
                ``source`` and the field.
        """
        base = base if base is not None else cls()
        if data is None:
            return dataclasses.replace(base)
        if not isinstance(data, Mapping):
            raise ConfigError(f"{source}: expected a mapping of tracker fields, "
                              f"got {type(data).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        removed = sorted(set(data) & set(_REMOVED_FIELDS))
        if removed:
            raise ConfigError(f"{source}: field {removed[0]!r} was removed: "
                              f"{_REMOVED_FIELDS[removed[0]]}")
        unknown = sorted(set(data) - set(fields))
        if unknown:
            raise ConfigError(f"{source}: {unknown_fields(unknown, fields)}")
        values: dict[str, Any] = {}
        for name, value in data.items():
            where = f"{source}: {name}"
            current = getattr(base, name)
            if name == "flow":
                values[name] = _flow_from(value, current, where)
            elif isinstance(current, VelocityKFConfig | PoseUKFConfig | FrameFlowConfig
                            | GEConfig):
                values[name] = _section_from(type(current), value, current, where)
            else:
                values[name] = checked_scalar(name, value, current, source)
        try:
            return dataclasses.replace(base, **values)
        except ConfigError as exc:
            if str(exc).startswith(source):
                raise
            raise ConfigError(f"{source}: {exc}") from exc

    @classmethod
    def from_yaml(cls, path: str | Path) -> TrackerConfig:
        """Load from a YAML file: the fields at top level, or under a ``tracker:`` key (the
        file's other top-level sections, e.g. ``sim:``, are then left to their readers)."""
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"{path}: cannot read tracker config ({exc})") from exc
        if data is None:
            data = {}
        if isinstance(data, Mapping) and "tracker" in data:
            # a file with several sections (e.g. tracker: and sim:) takes its tracker: one
            mixed = sorted(set(data) & {f.name for f in dataclasses.fields(cls)})
            if mixed:
                raise ConfigError(f"{path}: tracker fields {mixed} at the top level beside a "
                                  "'tracker:' section; put them in one place")
            data = data["tracker"]
        return cls.from_dict(data, source=str(path))

    def to_dict(self) -> dict[str, Any]:
        """Plain Python values (YAML-serialisable); ``from_dict(to_dict())`` gives it back."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, FlowConfig):
                value = value.to_dict()
            elif dataclasses.is_dataclass(value):
                value = dataclasses.asdict(value)
            out[f.name] = value
        return out

    def to_yaml(self, path: str | Path) -> None:
        from evtrack.utils import atomic_write_text

        atomic_write_text(path, yaml.safe_dump(self.to_dict(), sort_keys=False))


def load_tracker_config(path: str | Path) -> TrackerConfig:
    """:meth:`TrackerConfig.from_yaml`."""
    return TrackerConfig.from_yaml(path)


# ---------------------------------------------------------------------------- helpers
def _flow_from(value: Any, current: FlowConfig, where: str) -> FlowConfig:
    if value is None:
        return current
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a mapping of flow fields, got {value!r}")
    merged = current.to_dict()
    merged.update(value)
    try:
        return FlowConfig.from_dict(merged)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def _section_from(cls: type, value: Any, current: Any, where: str) -> Any:
    if value is None:
        return current
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: expected a mapping of {cls.__name__} fields, got {value!r}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(value) - names)
    if unknown:
        raise ConfigError(f"{where}: {cls.__name__}: {unknown_fields(unknown, names)}")
    merged = {n: getattr(current, n) for n in names}
    merged.update(value)
    if cls in (VelocityKFConfig, PoseUKFConfig, PoseTwistUKFConfig):
        return config_from_dict(cls, merged, where)
    converted = {n: checked_scalar(n, v, getattr(current, n), where) for n, v in merged.items()}
    try:
        return cls(**converted)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def _need_int(cfg: object, name: str, low: int) -> None:
    value = getattr(cfg, name)
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f"field {name!r} must be an integer >= {low}, got {value!r}")


def _need_positive(cfg: object, name: str) -> None:
    value = getattr(cfg, name)
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
            math.isfinite(value) and value > 0):
        raise ConfigError(f"field {name!r} must be a finite number > 0, got {value!r}")
