"""Configuration of :class:`evtrack.Tracker`: one dataclass with a section per part, loadable
from YAML.

``configs/tracker.yaml`` holds the defaults below. :meth:`TrackerConfig.from_dict` and
:meth:`TrackerConfig.from_yaml` read a (partial) mapping with the rules of
:mod:`evtrack.configs`: absent fields keep their documented defaults (a partial section keeps
the tracker's defaults of its other fields), unknown fields and values of the wrong type or
out of range raise a :class:`~evtrack.errors.ConfigError` that names the file and the field
(``flow.window_us``, ``pose_gate.depth_min_share``...). The flat keys of earlier versions
(``pose_depth_min_share``, ``depth_source``, ``realtime_load``...) still load, with a
:class:`~evtrack.configs.RenamedKeyWarning` naming the new key (:attr:`TrackerConfig.RENAMED_KEYS`).

Units: microseconds for event-clock quantities (``*_us``), milliseconds for latencies and
ages (``*_ms``), pixels, metres, radians, Hz.

Example:
    >>> cfg = TrackerConfig.from_dict({"method": "pose", "pose_rate_hz": 10})
    >>> cfg.method, cfg.pose_rate_hz, cfg.velocity_step_us
    ('pose', 10.0, 1000)
    >>> TrackerConfig.from_dict({"pose_gate": {"depth_min_share": 0.6}}).pose_gate.depth_min_share
    0.6
"""

from __future__ import annotations

import copy
import dataclasses
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

from evtrack import configs
from evtrack.configs import Config, FieldError, setting
from evtrack.denoise import DenoiseConfig
from evtrack.errors import ConfigError
from evtrack.filters.config import PoseTwistUKFConfig, PoseUKFConfig, VelocityKFConfig
from evtrack.flow.config import FlowConfig
from evtrack.tracking.config_sections import (
    AppearanceConfig,
    DepthConfig,
    DepthFusionConfig,
    FrameFlowConfig,
    GEConfig,
    LoadConfig,
    PoseGateConfig,
    RemeasureConfig,
)
from evtrack.tracking.methods import METHODS, method_names

__all__ = [
    "METHODS",
    "AppearanceConfig",
    "DepthConfig",
    "DepthFusionConfig",
    "FrameFlowConfig",
    "GEConfig",
    "LoadConfig",
    "PoseGateConfig",
    "RemeasureConfig",
    "TrackerConfig",
    "load_tracker_config",
]


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
    # A time window where more than half of the reported RoI windows have no constraint line is
    # judged strictly (FlowConfig.max_lineless_share): a real sensor's timestamp jitter leaves
    # most RoI windows of a slow scene with one unconfirmed candidate (ECD poster and boxes
    # clips: 75-78 % of them, median direction error 50-63 deg, every time window judged
    # strictly). On simulated objects it refuses 0.1-3 % of the RoI windows, on the slowest
    # (the tomato soup can at `regular`) 17-52 %.
    return FlowConfig(window_us=1000, roi_size=12, max_hypotheses=16, max_events_per_roi=32,
                      max_span_us=40_000, tolerance_rel=0.05, min_support=2, history=1,
                      max_lineless_share=0.5)


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
    # on the default `faster`). Those figures are of the fixed set it was chosen on. On the
    # benchmark's test split (2 seeds per cell, both speed settings, 2026-12-07, `evaluate
    # --methods full`) it changed the eight column averages by -0.15 to +0.12 cm and -0.10 to
    # +0.37 deg (mean gains 0.015 cm and 0.07 deg), far inside the seeds' spread: it has not
    # earned a place in the defaults, and is off (the paper's filter); `pose_ukf.velocity_bias:
    # true` turns it on, `evaluate --ablation` measures it (`full-velocity-bias`).
    # q_rotation 0.1 rad²/s: with the RoIs' depth range following the filter's uncertainty
    # (depth.range_sigmas) the event twist drifts less between poses than it does without,
    # and a tighter noise than 0.3 gates more of a network's gross errors about a can's axis.
    # Tuning split (12 `faster` sequences per speed setting, 4 `regular`), full, rotation
    # 0.3 -> 0.1:
    # paper-matched regular 6.93 -> 6.85, faster 11.17 -> 10.39 (one tomato can 20 -> 11);
    # default presets 7.79 -> 7.72, 11.48 -> 11.38; positions within 0.01 cm.
    return PoseUKFConfig(q_translation=0.01, q_rotation=0.1, reinit_after=3,
                         velocity_bias=False, q_velocity_bias=0.01, init_std_velocity_bias=0.05)


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
    # The full method's translation noise (_pose_ukf_defaults) and 0.3 rad²/s in rotation: the
    # dense-flow twist drifts as the event twist does, and a tighter noise made the gate reject
    # good poses (oracle poses, the four YCB `faster` sequences at 4 kHz: 28.4 cm / 39.7 deg
    # with the filter's defaults, 21.8 cm / 38.5 deg with these; 18.4 cm / 33.7 deg once the
    # frame pairs before a late first pose were measured too).
    return PoseTwistUKFConfig(q_translation=0.01, q_rotation=0.3)


_REMOVED_FIELDS = {
    "depth_range_scale": "the range is measured on surface points of the mesh in 4-px image "
                         "cells, not on a render (2026-11-28); delete the field",
}
"""Fields of earlier versions, with what to do instead (an error that says so, not a bare
"unknown field")."""


@dataclass
class TrackerConfig(Config):
    """Everything :class:`evtrack.Tracker` needs besides the cameras, the object and the sources.

    Attributes:
        method: ``"full"`` (the paper: event flow -> velocity KF -> pose UKF with poses),
            ``"velocity"`` (the twist integrated after the first pose only), ``"pose"`` (UKF with
            poses only), ``"frame-flow"`` (ROFT-like: dense RGB flow -> twist measurements of a
            constant-velocity pose UKF), ``"ge"`` (1-DoF generative event model).
        pose_source: where the absolute poses come from. ``"network"``: the pose source handed to
            the tracker (a trained pose network, :mod:`evtrack.tracking.pose_sources`), or poses
            pushed by the caller. ``"model"``: the object's mesh alone, nothing trained: from a
            start pose (:meth:`Tracker.reset`), the tracker corrects its pose with the mesh
            aligned to the depth frames (``depth_fusion``'s ICP, where ``depth.source`` is
            ``"sensor"``) and its textured render aligned to the RGB frames (``appearance``). A
            track that is lost stays lost until the next :meth:`Tracker.reset`. Not for
            ``"velocity"`` (its poses only initialise).
        device: torch device of the flow and the filters (``"cpu"``, ``"cuda"``).
        torch_threads: CPU threads torch (and the flow's compiled kernels, which follow torch's
            count) use during :meth:`Tracker.track`, restored after; never more than the cores this
            process may use; 0 leaves torch's setting. Two by default: on 2 cores the flow runs a
            third faster than on one (``benchmarks/bench_tracker.py --threads 1 2``: real-time
            factor 3.0 against 3.9) and the tiny per-step filter ops cost the same. Threads beyond
            the free cores are far slower (2 threads on 2 busy cores made a run 20x slower than 1),
            so ``evtrack evaluate --jobs N`` gives each job its share of the cores. Streaming
            callers set ``torch.set_num_threads`` themselves.
        blas_threads: numpy's BLAS threads while the tracker works (``track`` and the streaming
            calls), restored after each call; 0 leaves the library's setting. One by default: the
            tracker's numpy products are small, and OpenBLAS's idle workers spin after each larger
            one and take a core from the flow (see :mod:`evtrack.runtime.blas_threads`, also for
            trackers running in several threads at once: give them 0 and limit BLAS around them).
        velocity_step_us: the velocity filter runs once per step (µs); the tracker outputs a pose
            and a twist at the end of every step (1 kHz by default). Steps are aligned on absolute
            time (multiples of the step).
        flow_batch_steps: the event flow runs once per this many velocity steps (one call on their
            events, masked with the convex hull of the silhouette predicted at the first step and
            the one predicted at the last step's end with the current twist). The filters still step
            once per step and take the pose, its silhouette and the velocity filter's pivot afresh
            every 10 steps, as groups of 10 did. Groups of steps are aligned on absolute time, so
            results do not depend on how the events are chunked. The outputs of a group are
            available at its end: a delay of up to ``flow_batch_steps`` steps in live use
            (:meth:`Tracker.pose` extrapolates with the current twist meanwhile). 40 by default:
            each flow call has a fixed cost (a few ms of Python, small kernels, thread wake-ups),
            and 40 instead of 10 took about a third off the tracking time of three of the four
            `faster` YCB sequences on 2 cores of an AMD EPYC, 2026-12-02
            (`benchmarks/bench_tracker_options.py`; ``docs/results.md``, "Step groups of 40 ms and
            of 10 ms"), with the benchmark errors of groups of 10 to every digit except the default
            presets' cracker box `faster` (2.74 cm / 5.69 deg against 2.55 / 6.01) and the demo's
            seeds 0-5 at 6.12 cm / 12.27 deg against 5.94 / 12.55. For live use where the delay
            matters, 10 costs that time back.
        mask_margin_px: events are kept when they lie within this distance (pixels) of the object's
            predicted silhouette (the convex hull of the projected mesh). It must cover the
            predicted pose's error, or the events of one side are lost and the flow is biased: with
            oracle poses (1 cm, 0.03 rad noise) on the `faster` benchmark set, 8 px gave a rotation
            RMSE twice that of 32 px (cracker box: 10.3 vs 5.4 deg); 48 px gave the same as 32.
            Scale it with the image width.
        burst_rate_hz: a velocity step whose events outside the (grown) silhouette exceed this rate
            per pixel of the image outside it (events per pixel per second) is an event burst
            (flicker, a sensor glitch): its events are not used and the velocity filter only
            predicts; 0 disables. The object's own events cannot reach it (at 640x480 a fast object
            gives ~6 events per pixel per second over the whole image); sensor background activity
            is 0.1 to a few Hz per pixel. A step is a burst only when its rate is also above
            ``burst_factor`` times the median rate of the last ``burst_baseline_ms`` of steps.
        burst_baseline_ms: the window (ms) of that median, the stream's background activity
            outside the object. A moving camera's textured background fires above
            ``burst_rate_hz`` all the time: the median rises with it (within half the window),
            so its steps are not bursts, while a flicker on top of it still is. 0: the absolute
            rate alone (the test then assumes a static camera).
        burst_factor: how far above that median a burst step's rate is (a sudden rise).
        lost_after_ms: the object counts as lost when its predicted silhouette has stayed outside
            the image (less than ``min_visible_fraction`` of its hull area inside) for this long;
            the pose filter then waits for the next pose to re-initialise.
        min_visible_fraction: see ``lost_after_ms``.
        lost_after_misses: the object also counts as lost when this many pose-source calls in a row
            found nothing (or only detections below ``pose_gate.min_confidence``), counted when each
            result would have been available; 0 disables. A detector finds nothing once the object
            has left the image, while the prediction, without events to follow, can stop short
            inside it. With the default 3 at 5 Hz: 0.6 s without a detection.
        pose_rate_hz: the pose source runs on RGB frames at this rate (the paper: 5 Hz).
        pose_latency_ms: a pose computed from the frame at ``t`` becomes available to the filter at
            ``t + latency`` (simulated offline; the filter rolls back to ``t`` to fuse it).
            Default: one pose period (a network just fast enough for its rate). The method
            paper states no latency for its tables; 0 fuses each pose at its frame's time.
        pose_async: in :meth:`~evtrack.tracking.tracker.Tracker.track` (offline), run the pose
            source in a worker thread of the tracker (one, so calls keep the frames' order) and take
            its result when it becomes available to the filter (``pose_latency_ms`` after the
            frame): the same trajectory and statistics as calling it at the frame (the tests compare
            both), while the network's time and the RGB frame's decoding overlap the event tracking
            (a pose-network call on a CPU takes 20-40 ms; the tracking runs mostly on one core). The
            pose source is then called from that thread, within ``track``'s BLAS limit where the
            library's limit is process-wide (OpenBLAS, as in numpy's wheels); its exception surfaces
            from ``track``. A result due at once (``pose_latency_ms`` 0) is computed at once. The
            streaming calls always run the pose source in the caller's thread: a live application
            runs its network where it likes and hands the poses to
            :meth:`~evtrack.tracking.tracker.Tracker.push_pose`.
        pose_prior: while the track holds, hand the pose source the tracker's pose at the frame's
            time (``prior=``, to sources whose ``accepts_prior`` is true:
            :class:`~evtrack.tracking.pose_sources.NetworkPoseSource`), which looks for the object
            there first: the network then runs once, on a crop around that pose, instead of on the
            whole image and then on a crop (:meth:`~evtrack.models.PoseEstimator.estimate_near`; the
            whole image again when the crop does not find the object near its centre). Before the
            first pose and after a loss, no prior: the whole image.
        history_ms: how far back the pose filter keeps its past states for late poses; a pose older
            than that is dropped and counted.
        use_flow_normal_flags: pass the flow's per-RoI aperture flags to the velocity filter
            (normal-only rows where the flow saw one edge direction). Off, every RoI gets
            ``velocity_kf.assume_normal`` (the paper treats every flow as a normal flow).
        pivot_max_radius_ratio: with ``velocity_kf.object_centred`` the velocity filter's process
            noise pivots on the object's centre, as an object moving before a still camera
            turns about itself. An object whose radius (its farthest vertex from its origin) is
            at least this share of its distance is taken for a scene around the camera (a
            camera recording imported with its scene as the object, e.g. a plane filling the
            view): what moves is the camera, which turns about itself, so the noise has no
            pivot there.
        pose_gate: the pose gate (:class:`~evtrack.tracking.config_sections.PoseGateConfig`): depth
            check, ray alignment, alternatives, half turns, re-initialisation on agreement.
        depth: the depth at the RoIs (:class:`~evtrack.tracking.config_sections.DepthConfig`):
            sensor or model depth.
        depth_fusion: the RGB-D extensions
            (:class:`~evtrack.tracking.config_sections.DepthFusionConfig`): range and ICP
            measurements from the depth frames.
        appearance: poses from the RGB frames aligned with the textured mesh's render
            (:class:`~evtrack.tracking.config_sections.AppearanceConfig`).
        load: the work per step (:class:`~evtrack.tracking.config_sections.LoadConfig`): event and
            search budgets, real-time load control.
        remeasure: the steps before the first pose
            (:class:`~evtrack.tracking.config_sections.RemeasureConfig`).
        denoise: sensor noise removed from the events as they are pushed, before the gate and
            the flow (:class:`~evtrack.denoise.DenoiseConfig`: a background-activity filter,
            hot pixels; off by default), counted in ``TrackerStats.events_denoised``,
            ``events_on_hot_pixels`` and ``hot_pixels``. Only for the methods that use events.
        flow: the event optical flow (:class:`~evtrack.flow.FlowConfig`); ``velocity_step_us`` must
            be a multiple of ``flow.window_us``. The tracker's defaults differ from the flow's: 1 ms
            windows, 12 px RoIs, Eq. 3 over 16 hypotheses from 32 events, triplets over at most 40
            ms with a 5 % tolerance (fast objects; for slow motion ``configs/tracker_slow.yaml``)
            from the last event of each pixel and polarity. The measurements behind them are in this
            module's source (``_tracker_flow_defaults``).
        velocity_kf: the velocity Kalman filter (ablations: ``normal_flow``, ``weighting``).
        pose_ukf: the pose UKF of ``full``, ``velocity`` and ``ge``.
        pose_only_ukf: the pose UKF of the ``pose`` baseline (random-walk process noise).
        pose_twist_ukf: the constant-velocity pose UKF of ``frame-flow``.
        frame_flow: dense RGB flow settings of ``frame-flow``.
        frame_flow_kf: the velocity filter that turns one frame pair's flows into a twist
            measurement (``frame-flow``).
        ge: the generative event model of ``ge``.
    """

    RENAMED_KEYS: ClassVar[Mapping[str, str]] = {
        "pose_min_confidence": "pose_gate.min_confidence",
        "pose_depth_min_share": "pose_gate.depth_min_share",
        "pose_depth_tolerance_m": "pose_gate.depth_tolerance_m",
        "pose_depth_align": "pose_gate.depth_align",
        "pose_depth_align_max_m": "pose_gate.depth_align_max_m",
        "pose_alternatives": "pose_gate.alternatives",
        "pose_alternatives_min_confidence": "pose_gate.alternatives_min_confidence",
        "pose_half_turn_axes": "pose_gate.half_turn_axes",
        "pose_half_turn_max_view_deg": "pose_gate.half_turn_max_view_deg",
        "pose_half_turn_reinit_after": "pose_gate.half_turn_reinit_after",
        "reinit_on_agreement": "pose_gate.reinit_on_agreement",
        "reinit_agree_m": "pose_gate.reinit_agree_m",
        "reinit_agree_m_per_s": "pose_gate.reinit_agree_m_per_s",
        "reinit_agree_deg": "pose_gate.reinit_agree_deg",
        "reinit_agree_deg_per_s": "pose_gate.reinit_agree_deg_per_s",
        "depth_source": "depth.source",
        "depth_patch_px": "depth.patch_px",
        "depth_stride_px": "depth.stride_px",
        "max_depth_age_ms": "depth.max_age_ms",
        "model_depth_interval_us": "depth.model_interval_us",
        "model_depth_scale": "depth.model_scale",
        "depth_range": "depth_fusion.range",
        "depth_range_std_m": "depth_fusion.range_std_m",
        "depth_icp": "depth_fusion.icp",
        "depth_icp_rate_hz": "depth_fusion.icp_rate_hz",
        "depth_icp_points": "depth_fusion.icp_points",
        "depth_icp_scene_points": "depth_fusion.icp_scene_points",
        "depth_icp_std_m": "depth_fusion.icp_std_m",
        "depth_icp_std_deg": "depth_fusion.icp_std_deg",
        "max_events_per_step": "load.max_events_per_step",
        "search_per_roi_window": "load.search_per_roi_window",
        "max_searched_per_step": "load.max_searched_per_step",
        "realtime_load": "load.realtime",
        "min_searched_per_step": "load.min_searched_per_step",
        "min_events_per_step": "load.min_events_per_step",
        "velocity_before_pose": "remeasure.before_pose",
        "remeasure_on_pose": "remeasure.on_pose",
        "remeasure_min_inside": "remeasure.min_inside",
    }
    """The flat keys of earlier versions -> their place in the sections."""

    method: str = "full"
    pose_source: Literal["network", "model"] = "network"
    device: str = "cpu"
    torch_threads: int = setting(2, ge=0)
    blas_threads: int = setting(1, ge=0)
    velocity_step_us: int = setting(1000, ge=1, unit="µs")
    flow_batch_steps: int = setting(40, ge=1)
    mask_margin_px: float = setting(32.0, ge=0, unit="px")
    burst_rate_hz: float = setting(100.0, ge=0, unit="Hz")
    burst_baseline_ms: float = setting(100.0, ge=0, unit="ms")
    burst_factor: float = setting(4.0, ge=1)
    lost_after_ms: float = setting(100.0, ge=0, unit="ms")
    min_visible_fraction: float = setting(0.05, ge=0, le=1)
    lost_after_misses: int = setting(3, ge=0)
    pose_rate_hz: float = setting(5.0, gt=0, unit="Hz")
    pose_latency_ms: float = setting(200.0, ge=0, unit="ms")
    pose_async: bool = True
    pose_prior: bool = False
    history_ms: float = setting(1000.0, gt=0, unit="ms")
    use_flow_normal_flags: bool = True
    pivot_max_radius_ratio: float = setting(0.5, gt=0)
    pose_gate: PoseGateConfig = field(default_factory=PoseGateConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    depth_fusion: DepthFusionConfig = field(default_factory=DepthFusionConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    load: LoadConfig = field(default_factory=LoadConfig)
    remeasure: RemeasureConfig = field(default_factory=RemeasureConfig)
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    flow: FlowConfig = field(default_factory=_tracker_flow_defaults)
    velocity_kf: VelocityKFConfig = field(default_factory=VelocityKFConfig)
    pose_ukf: PoseUKFConfig = field(default_factory=_pose_ukf_defaults)
    pose_only_ukf: PoseUKFConfig = field(default_factory=_pose_only_defaults)
    pose_twist_ukf: PoseTwistUKFConfig = field(default_factory=_pose_twist_defaults)
    frame_flow: FrameFlowConfig = field(default_factory=FrameFlowConfig)
    frame_flow_kf: VelocityKFConfig = field(default_factory=_frame_flow_kf_defaults)
    ge: GEConfig = field(default_factory=GEConfig)

    def __post_init__(self) -> None:
        self._sections_from_mappings()
        super().__post_init__()
        if self.method not in method_names():
            raise FieldError(self, "method", f"must be one of {method_names()}, got "
                             f"{self.method!r}")
        if self.pose_source == "model" and self.method == "velocity":
            raise FieldError(self, "pose_source",
                             "'model' corrects the pose all along; the 'velocity' method takes "
                             "poses only to start (give it a start pose with Tracker.reset)")
        for name in ("range", "icp"):
            if getattr(self.depth_fusion, name) and self.depth.source != "sensor":
                raise FieldError(self, f"depth_fusion.{name}",
                                 f"needs depth.source 'sensor' (got {self.depth.source!r}): "
                                 "it measures on the RGB-D depth frames")
        if self.velocity_step_us % self.flow.window_us:
            raise FieldError(self, "velocity_step_us",
                             f"({self.velocity_step_us}) must be a multiple of flow.window_us "
                             f"({self.flow.window_us}) so that every step's flows are complete "
                             "at its end")
        if self.pose_rate_hz > 1e6 / self.velocity_step_us:
            raise FieldError(self, "pose_rate_hz",
                             f"({self.pose_rate_hz:g}) must not exceed one pose per velocity "
                             f"step ({1e6 / self.velocity_step_us:g} Hz)")
        if self.history_ms < self.pose_latency_ms + 1e3 / self.pose_rate_hz:
            raise FieldError(self, "history_ms",
                             f"({self.history_ms}) must cover pose_latency_ms "
                             f"({self.pose_latency_ms}) plus one pose period "
                             f"({1e3 / self.pose_rate_hz:g} ms)")

    def _sections_from_mappings(self) -> None:
        """Built in code, a section may be given as a mapping of its fields
        (``velocity_kf={"flow_std": 20.0}``): it becomes the section, its other fields at the
        tracker's defaults. Every field's type is checked as the loader checks it
        (``TrackerConfig(depth_fusion={"icp": "false"})`` must not turn ICP on)."""
        defaults = None
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Mapping):
                defaults = defaults if defaults is not None else type(self)()
                merged = configs.to_dict(getattr(defaults, f.name))
                merged.update(value)
                value = configs.convert_value(merged, hints[f.name], f"TrackerConfig.{f.name}")
            elif not dataclasses.is_dataclass(value):
                value = configs.convert_value(value, hints[f.name], f"TrackerConfig.{f.name}")
            elif not isinstance(value, hints[f.name]):
                raise FieldError(self, f.name, f"must be a {hints[f.name].__name__} or a "
                                 f"mapping of its fields, got {type(value).__name__}")
            object.__setattr__(self, f.name, value)

    # ------------------------------------------------------------------ derived values
    @property
    def uses_depth_icp(self) -> bool:
        """Whether the depth frames are aligned with the mesh: ``depth_fusion.icp``, or
        ``pose_source: model`` with sensor depth."""
        return self.depth_fusion.icp or (self.pose_source == "model"
                                         and self.depth.source == "sensor")

    @property
    def icp_min_information(self) -> float:
        """``depth_fusion.icp_min_information``, or its default where it is ``None``: 0.01 with
        the appearance alignment on, else 0."""
        share = self.depth_fusion.icp_min_information
        if share is not None:
            return share
        return 0.01 if self.uses_appearance else 0.0

    @property
    def uses_appearance(self) -> bool:
        """Whether the RGB frames are aligned with the textured mesh: ``appearance.enabled``,
        or ``pose_source: model``."""
        return self.appearance.enabled or self.pose_source == "model"

    @property
    def pose_period_us(self) -> int:
        """The pose source's period in µs."""
        return int(round(1e6 / self.pose_rate_hz))

    @property
    def pose_latency_us(self) -> int:
        """``pose_latency_ms`` in µs."""
        return int(round(self.pose_latency_ms * 1e3))

    # ------------------------------------------------------------------ loading
    def replace(self, **changes: Any) -> TrackerConfig:
        """A copy with some top-level fields (or whole sections) changed (validated again)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None, source: str = "tracker config",
                  base: TrackerConfig | None = None) -> TrackerConfig:
        """Build from a (partial) mapping; absent fields keep the defaults (or ``base``'s), a
        partial section keeps the other fields of the base's section.

        Raises:
            ConfigError: an unknown field, a value of the wrong type or out of range, naming
                ``source`` and the field.
        """
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise ConfigError(f"{source}: expected a mapping of tracker fields, "
                              f"got {type(data).__name__}")
        removed = sorted(set(data) & set(_REMOVED_FIELDS))
        if removed:
            raise ConfigError(f"{source}: field {removed[0]!r} was removed: "
                              f"{_REMOVED_FIELDS[removed[0]]}")
        data = configs.move_renamed(cls, data, source)
        merged = _merged((base if base is not None else cls()).to_dict(), data)
        return configs.from_dict(cls, merged, source)

    @classmethod
    def from_yaml(cls, path: str | Path, overrides: tuple[str, ...] = ()) -> TrackerConfig:
        """Load from a YAML file: the fields at top level, or under a ``tracker:`` key (the
        file's other top-level sections, e.g. ``sim:``, are then left to their readers);
        ``section.field=value`` overrides applied."""
        data = configs.read_yaml(path)
        if isinstance(data, Mapping) and "tracker" in data:
            # a file with several sections (e.g. tracker: and sim:) takes its tracker: one
            known = {f.name for f in dataclasses.fields(cls)} | set(cls.RENAMED_KEYS)
            mixed = sorted(set(data) & known)
            if mixed:
                raise ConfigError(f"{path}: tracker fields {mixed} at the top level beside a "
                                  "'tracker:' section; put them in one place")
            data = data["tracker"]
        if overrides:
            data = configs.apply_overrides(data or {}, overrides)
        return cls.from_dict(data, source=str(path))


def _merged(base: Mapping[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``changes`` laid over it, section by section."""
    out = copy.deepcopy(dict(base))
    for key, value in changes.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _merged(out[key], value)
        else:
            out[key] = value
    return out


def load_tracker_config(path: str | Path) -> TrackerConfig:
    """:meth:`TrackerConfig.from_yaml`."""
    return TrackerConfig.from_yaml(path)
