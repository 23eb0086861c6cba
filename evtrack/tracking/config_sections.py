"""The sections of :class:`~evtrack.tracking.config.TrackerConfig`: the pose gate, the depth at
the RoIs, the RGB-D depth fusions, the appearance alignment, the work per step (and real-time
load control), the steps before the first pose, and the frame-flow and GE baselines.

Each is a :class:`~evtrack.configs.Config` dataclass: its ranges and units are declared on its
fields and checked whether it is built in code or read from YAML.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from evtrack.configs import Config, FieldError, setting
from evtrack.tracking.pose_flips import HalfTurnResolver

__all__ = [
    "AppearanceConfig",
    "DepthConfig",
    "DepthFusionConfig",
    "FrameFlowConfig",
    "GEConfig",
    "LoadConfig",
    "PoseGateConfig",
    "RemeasureConfig",
]


@dataclass
class FrameFlowConfig(Config):
    """The ``frame-flow`` baseline (ROFT-like): dense optical flow between consecutive RGB frames.

    Attributes:
        algorithm: ``"dis"`` (OpenCV's DIS optical flow) or ``"farneback"``.
        dis_preset: DIS preset: ``"ultrafast"``, ``"fast"`` or ``"medium"``.
        grid_px: flow samples are taken on a grid of this pitch (pixels, event-camera image)
            inside the predicted object silhouette.
        max_gap_ms: two frames further apart than this (dropped frames) give no flow.
        max_samples: at most this many grid samples per frame pair (evenly thinned).
    """

    algorithm: Literal["dis", "farneback"] = "dis"
    dis_preset: Literal["ultrafast", "fast", "medium"] = "medium"
    grid_px: int = setting(16, ge=1, unit="px")
    max_gap_ms: float = setting(50.0, gt=0, unit="ms")
    max_samples: int = setting(400, ge=1)


@dataclass
class GEConfig(Config):
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

    contrast: float = setting(0.2, gt=0)
    blur_sigma_px: float = setting(1.0, gt=0, unit="px")
    min_gradient: float = setting(0.02, ge=0, unit="1/px")
    max_dt_ms: float = setting(3.0, gt=0, unit="ms")
    residual_std: float = setting(0.3, gt=0)
    max_events: int = setting(2000, ge=1)
    log_eps: float = setting(0.01, gt=0)


@dataclass
class PoseGateConfig(Config):
    """What becomes of a pose before the pose filter fuses it
    (:mod:`evtrack.tracking.pose_gate`).

    Attributes:
        min_confidence: detections below this confidence are ignored (they count as misses, see
            ``lost_after_misses``).
        depth_min_share: a pose (from the pose source or :meth:`Tracker.push_pose`) is dropped
            (counted in ``TrackerStats.poses_implausible``) when, of the valid sensor-depth pixels
            inside its silhouette (sampled every 4 px, on the depth frame nearest the pose's time:
            the sensor maps of the last ``history_ms`` are kept for poses that arrive late), fewer
            than this share lie in the object's depth range at that pose widened by
            ``depth_tolerance_m``: the depth shows that the object is not where the pose puts it. A
            network can only see what is visible, so a right pose has most of its silhouette at its
            own depth; occluders count against it, hence a share below 1. It stops gross network
            errors (e.g. a bottle seen from below, turned half a turn and pushed a metre back:
            shares 0-0.33, right poses 0.6-1.0 on the benchmark) from re-initialising the filter. 0:
            off; no check without a sensor depth frame within ``depth.max_age_ms`` of the pose or
            with fewer than 16 valid pixels.
        depth_tolerance_m: see ``depth_min_share``.
        depth_align: before that check, move each pose along its viewing ray until the object's
            surface at the pose lies on its frame's sensor depth
            (:class:`~evtrack.tracking.pose_alignment.PoseRayAligner`; rotation and the position
            across the ray kept). An RGB network errs mostly in range: the mustard bottle's poses on
            the paper-matched `faster` sequence were 11-14 cm off along the ray and under 1 cm
            across it, 0.2-0.7 cm after the alignment. Needs the object's mesh with faces and a
            sensor depth frame (as the check); a pose is left as it is when too few image cells see
            both its surface and a valid depth, when they disagree (the pose is off across the ray
            or turned), or when the move would exceed ``depth_align_max_m``. Not in the paper (its
            pose network uses RGB only).
        depth_align_max_m: the largest move of ``depth_align``, metres: a pose farther off is a
            gross error for the check to drop, not to move onto whatever lies behind it.
        alternatives: where a pose fails that check, try the other poses its detector found in the
            same image (:attr:`~evtrack.tracking.pose_sources.PoseMeasurement.alternatives`, e.g.
            the first pass's detection where the network's crop pass replaced it, or the strongest
            peaks' fit where the corner search's was kept), most confident first, each aligned and
            checked the same way; the first that passes is used in its place (counted in
            ``TrackerStats.poses_from_alternatives``). The depth, not the confidence, picks among
            them: on the mustard bottle's end-on frames the kept pose had confidence 0.00 and lay
            0.6 m off while the first pass's (0.15) lay at the right range. Needs the same as the
            check; off or without alternatives, the pose is just dropped. Not in the paper.
        alternatives_min_confidence: alternatives less confident than this (or than
            ``min_confidence``) are not tried. A corner-identity confusion can give a pose turned
            half a turn at the right range, which the depth confirms: on the benchmark the
            alternatives the depth confirmed had confidences 0.64-0.85 and lay 2-9° off, except one
            of 0.15 turned 176°, which the ``pose`` baseline (no events to hold its filter) then
            fused (mustard bottle, paper-matched `faster`: 84° instead of 29°).
        half_turn_axes: the object-frame axes (a string of ``x``, ``y``, ``z``; ``""``: none) whose
            half turns the pose network may confuse where it sees the object along them: each pose
            seen within ``half_turn_max_view_deg`` of one of these axes is replaced by its half turn
            about that axis (through the cuboid's centre) when that lies nearer the filter's pose at
            the pose's time, in rotation (:class:`~evtrack.tracking.pose_flips.HalfTurnResolver`;
            counted in ``TrackerStats.poses_half_turned``). A cuboid-keypoint network's corner swaps
            give exactly these poses, at the right range, and seen along the axis their silhouettes
            agree, so the depth check cannot drop them (the mustard bottle seen from below: ``y``).
            Applied after the depth check, once the filter is initialised; the pose's covariance is
            kept. Not in the paper.
        half_turn_max_view_deg: see ``half_turn_axes``, degrees in [0, 90].
        half_turn_reinit_after: the filter re-initialises on the pose as it is (not turned) when
            this many fused poses in a row needed the turn: a network that turns its poses now and
            then does not turn several in a row, a track that started on a turned pose disagrees
            with every right one (0: never; the turned track is then corrected only once the views
            leave the axes' cones).
        reinit_on_agreement: when a pose is rejected by the pose filter's gate right after another
            rejected pose and the two agree with each other (the second within ``reinit_agree_m +
            reinit_agree_m_per_s * dt`` metres and ``reinit_agree_deg + reinit_agree_deg_per_s *
            dt`` degrees of the first, ``dt`` seconds later), the filter re-initialises on the
            second: the filter has drifted off, the poses have not. Random outliers rarely agree
            with each other, so they stay rejected (the filter's ``reinit_after`` still
            re-initialises after that many rejections in a row, agreeing or not).
        reinit_agree_m, reinit_agree_m_per_s, reinit_agree_deg, reinit_agree_deg_per_s: see
            ``reinit_on_agreement``.
    """

    min_confidence: float = setting(0.0, ge=0)
    depth_min_share: float = setting(0.5, ge=0, le=1)
    depth_tolerance_m: float = setting(0.06, ge=0, unit="m")
    depth_align: bool = True
    depth_align_max_m: float = setting(0.2, gt=0, unit="m")
    alternatives: bool = True
    alternatives_min_confidence: float = setting(0.3, ge=0)
    half_turn_axes: str = ""
    half_turn_max_view_deg: float = setting(30.0, ge=0, le=90, unit="deg")
    half_turn_reinit_after: int = setting(2, ge=0)
    reinit_on_agreement: bool = True
    reinit_agree_m: float = setting(0.05, ge=0, unit="m")
    reinit_agree_m_per_s: float = setting(1.0, ge=0, unit="m/s")
    reinit_agree_deg: float = setting(10.0, ge=0, unit="deg")
    reinit_agree_deg_per_s: float = setting(180.0, ge=0, unit="deg/s")

    def __post_init__(self) -> None:
        super().__post_init__()
        try:  # the resolver's own checks of both fields
            HalfTurnResolver(self.half_turn_axes, np.zeros(3), self.half_turn_max_view_deg)
        except ValueError as exc:
            raise FieldError(self, "half_turn_axes", str(exc)) from exc


@dataclass
class DepthConfig(Config):
    """Where the depth at the RoIs comes from (:mod:`evtrack.tracking.roi_depth`).

    Attributes:
        source: ``"sensor"`` (the RGB-D depth frames, carried into the event camera) or ``"model"``
            (depth rendered from the mesh at the predicted pose).
        patch_px: the depth of a RoI is the median of the valid depths within this radius (pixels,
            square patch) of its centre that lie inside the predicted silhouette.
        stride_px: pitch of the depth samples in that patch (pixels).
        max_age_ms: a sensor depth frame older than this is not used; RoIs then take the fallback
            depth (the predicted depth of the object's origin) and are counted.
        model_interval_us: the ``model`` depth map is re-rendered at most this often.
        model_scale: the ``model`` depth map is rendered at this fraction of the event camera's
            resolution.
        range_sigmas: a RoI's depths count as the object's within the depth range of its
            silhouette at the predicted pose, widened by
            :data:`~evtrack.tracking.roi_depth.DEPTH_TOLERANCE_M` plus this many standard
            deviations of the pose filter's uncertainty in the depth (camera ``z``) of the
            object's origin, taken at each segment's start. While the pose drifts (fast turns
            between two poses) its predicted range does too; a fixed margin then rejects the
            object's true depths and every RoI falls back to the drifted pose's depth, which
            scales the twist wrongly and drifts the pose further. 0: the fixed margin only.
    """

    source: Literal["sensor", "model"] = "sensor"
    patch_px: int = setting(16, ge=0, unit="px")
    stride_px: int = setting(4, ge=1, unit="px")
    max_age_ms: float = setting(100.0, ge=0, unit="ms")
    model_interval_us: int = setting(5000, ge=1, unit="µs")
    model_scale: float = setting(0.5, gt=0, le=1)
    range_sigmas: float = setting(3.0, ge=0)


@dataclass
class DepthFusionConfig(Config):
    """The RGB-D extensions (not in the paper): measurements of the pose from the sensor depth
    frames (:mod:`evtrack.tracking.depth_fusion`).

    Attributes:
        range: fuse the object's range along its viewing ray, measured on every sensor depth frame
            against the mesh's surface at the predicted pose (:mod:`evtrack.tracking.depth_range`),
            into the pose filter: the depth the event flow sees worst. Off by default (the paper's
            method uses depth only for the flow's interaction matrix); needs ``depth.source:
            sensor`` and the object's mesh (with faces). Not used by ``velocity``, which takes poses
            only to initialise.
        range_std_m: the floor of a range measurement's standard deviation (m).
        icp: align the object's mesh with sensor depth frames (point-to-plane ICP,
            :class:`~evtrack.models.DepthRefiner`) from the filter's pose at each frame's time and
            fuse the aligned pose (:meth:`~evtrack.filters.PoseUKF.update_aligned`) with the fit's
            own covariance: what the depth cannot see (a can turning about its axis, sliding within
            a face seen head-on) stays with the events and the pose source. The event flow sees an
            object's turn about an axis across the image barely apart from a shift; the depth sees
            it. Off by default (not in the paper); needs ``depth.source: sensor`` and the object's
            mesh. Not used by ``velocity``.
        icp_rate_hz: at most this many depth frames per second are aligned (each costs 13-17 ms of
            one CPU core with the defaults below, for a YCB object at 640x480: ``track`` took
            3.6-3.8 s for the 2 s of the mustard bottle ``faster`` instead of 2.5-2.8, 10.6-11.0 s
            for the cracker box instead of 10.1-10.5, on 2 cores).
        icp_points: mesh surface samples of the fit (about half face the camera).
        icp_scene_points: most depth pixels around the object used by the fit.
        icp_std_m, icp_std_deg: floors added to the fit's translation and rotation standard
            deviations (m, degrees): the fit's own covariance assumes independent depth errors,
            which a real sensor's (ripple, flying pixels, a scale bias) are not.
        icp_min_information: directions of the fit whose information (per metre of surface
            motion: rotations times the object's radius) is below this share of the best-seen
            direction's count as unseen (a huge variance): a near-symmetric shape's fit claims
            to see its symmetry (the fine ridges of a can's lids) far better than it does. 0:
            only directions below 1e-9 of the best. ``None`` (the default): 0.01 where the
            appearance alignment measures what the depth barely sees (``appearance`` on, as
            with ``pose_source: model``), else 0. On the tuning split's frames (YCB objects,
            simulated depth) the weakest direction's share was 0.004-0.006 for the tomato soup
            can (its spin), 0.008-0.022 for the mustard bottle, 0.036-0.107 for the box-like
            objects. With the mesh alone, 0.01 took the mean rotation error on the fixed set
            from 1.40° to 1.27° (0.03: 1.58°); with the networks, the default presets, it
            raised it from 1.49° to 2.82° (the can's `faster`: 2.1° to 10.8°): there the
            depth's hint about the can's spin beats the network's guesses.
    """

    range: bool = False
    range_std_m: float = setting(0.005, gt=0, unit="m")
    icp: bool = False
    icp_rate_hz: float = setting(30.0, gt=0, unit="Hz")
    icp_points: int = setting(1000, gt=0)
    icp_scene_points: int = setting(3000, gt=0)
    icp_std_m: float = setting(0.002, gt=0, unit="m")
    icp_std_deg: float = setting(1.0, gt=0, unit="deg")
    icp_min_information: float | None = setting(None, ge=0, le=1)


@dataclass
class AppearanceConfig(Config):
    """Poses measured from the RGB frames with the textured mesh, nothing trained
    (:mod:`evtrack.tracking.appearance_fusion`, :class:`~evtrack.models.AppearanceRefiner`):
    the mesh is rendered at the filter's pose of a frame's time and the frame aligned with the
    render; the aligned pose is fused with the fit's covariance. It sees what depth cannot (a
    can's turn about its axis shows only in its label) and little of the distance along the
    viewing ray (the depth's part). Part of ``TrackerConfig.pose_source: model``; with a pose
    network it can be turned on alone (``enabled``).

    Attributes:
        enabled: align RGB frames with the mesh's render and fuse the result (on whenever
            ``TrackerConfig.pose_source`` is ``"model"``). Needs the object's textured mesh.
        rate_hz: at most this many RGB frames per second are aligned. Each alignment costs
            75-140 ms of one CPU core for a YCB object at 640x480 (2 renders with Mesa's
            CPU OpenGL, 3 blur levels; ``benchmarks/bench_mesh_only.py``).
        levels: the Gaussian blurs (px) of the coarse-to-fine passes; the first sets how far the
            fit reaches.
        iterations: Levenberg-Marquardt steps per pass at most.
        max_pixels: template pixels per pass at most (the strongest texture gradients).
        min_correlation: the frame's and the render's luminance must correlate at least this
            well after the fit, or the fit is refused (counted as ``"low correlation"``).
        max_rotation_deg, max_translation_m: larger corrections are refused: past the fit's
            reach, it finds another minimum.
        cov_scale: the fit's covariance (residual variance x the inverse of its normal
            matrix) is multiplied by this: neighbouring pixels' errors are not independent (the
            blur, the frame's motion blur, the texture's resampling). On the simulator's
            `faster` sequences the normalised squared errors of fits from 5-30° off were ~25x
            their expected value (median 150-220 for 6 degrees of freedom).
        std_m, std_deg: floors added to the fit's translation and rotation standard
            deviations (m, degrees).
    """

    enabled: bool = False
    rate_hz: float = setting(10.0, gt=0, unit="Hz")
    levels: tuple[float, ...] = setting((4.0, 2.0, 1.0), gt=0, unit="px")
    iterations: int = setting(10, ge=1)
    max_pixels: int = setting(3000, ge=1)
    min_correlation: float = setting(0.5, ge=-1, le=1)
    max_rotation_deg: float = setting(45.0, gt=0, unit="deg")
    max_translation_m: float = setting(0.1, gt=0, unit="m")
    cov_scale: float = setting(25.0, gt=0)
    std_m: float = setting(0.003, gt=0, unit="m")
    std_deg: float = setting(1.0, gt=0, unit="deg")

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.levels:
            raise FieldError(self, "levels", "must name at least one blur (px)")


@dataclass
class LoadConfig(Config):
    """The work per velocity step: event and search budgets, and real-time load control
    (:mod:`evtrack.tracking.load_control`, :mod:`evtrack.tracking.event_gate`).

    Attributes:
        max_events_per_step: at most this many events per velocity step (on average over a step
            group) enter the flow (or the GE model); above it they are thinned by whole cells of 2 x
            2 RoIs, deterministically, and counted (see :mod:`evtrack.tracking.event_gate`), which
            bounds the work per step; 0: no cap. Thinning costs accuracy: on the cracker box
            `faster` (8.6 M events/s) 4000 gave 9.2 cm / 13.8 deg against 4.35 / 6.5 unthinned, in
            0.4x the time (real-time factor 10.1 -> 4.0). The default is ~5x the peak rate of the
            fast 640x480 simulated sequences (3.8k events per ms on the whole sensor).
        search_per_roi_window: the flow searches at most about this many events of one RoI window
            for candidates, a sample by the hash that also picks the registration's data term
            (:func:`evtrack.flow.sampling.sampled_search`); all events still enter the search's
            history, so the searched events' triplets are those of the whole stream, and a window
            whose sample holds ``flow.max_events_per_roi`` candidate-bearing events registers the
            same flow as unsampled. 0: search all.
        max_searched_per_step: at most this many of those events per velocity step (on average over
            a step group) are searched, by whole RoIs visited in a fixed hash order and taken while
            they fit (:func:`~evtrack.flow.sampling.sampled_search`'s ``budget``); the other RoIs'
            events still enter the history, so a taken RoI's flow is the one it would have without
            the budget and only the left-out RoIs give no flow. It bounds the flow's search and
            registration, its dominant costs, whatever the event rate. 0: no bound. On the four YCB
            objects' benchmark set (4 kHz, oracle poses) only the cracker box `faster` (8.6 M
            events/s, ~5k sampled events per ms) reaches 2500 after its first pose: 3.90 cm / 4.98
            deg without a budget, 3.90 / 4.74 with 2500 (3000: 4.16 / 4.90; 2000: 4.13 / 5.23; 1500:
            4.46 / 4.78; 1000: 5.24 / 5.84); the tomato can `regular`'s first 200 ms (all events,
            before the first pose) move a little (5.53 -> 4.91 deg); the other sequences are
            unchanged.
        realtime: keep up with a live stream: the processing of the step groups (the flow, the
            filters and the frames taken meanwhile) beyond this share of their stream time
            accumulates as a backlog; while the backlog exceeds 5 groups and the load (smoothed over
            ~10 groups) stays above this share, the search budget per step and the events per step
            (thinned by cells, as by ``max_events_per_step``) are cut together for the next groups,
            down to ``min_searched_per_step`` and ``min_events_per_step``; while there is no backlog
            both are raised again towards ``max_searched_per_step`` and ``max_events_per_step``
            (:class:`~evtrack.tracking.load_control.LoadController`). The budgets then follow the
            machine's speed and load, and so do the results: 0 (the default) keeps them
            deterministic. Needs ``max_searched_per_step > 0``. The work no budget bounds (reading
            and masking every event, the filters and the pose fusions: ~0.7-0.8 of real time on 2
            cores of a slow AMD EPYC with few events, 2026-12-02) stays. Shedding events costs
            accuracy: see ``docs/results.md``, "Live use: load.realtime".
        min_searched_per_step: the lowest search budget ``realtime`` goes to.
        min_events_per_step: the lowest event budget ``realtime`` goes to; 0: it never sheds events
            (only the search budget adapts). The floors bound the accuracy lost: on the cracker box
            `faster` (its network at 5 Hz, 2 cores of a slow AMD EPYC, 2026-12-02) 1000 and 2000
            gave 3.9-4.2 cm / 9.4-10.5 deg at 1.25-1.34 of real time (2.74 / 5.69 at 1.75-2.4
            without ``realtime``; the search budget alone down to 250: 5.4-5.7 / 10-12.3 at
            1.34-1.64; 250 and 500: 10.6 / 17-19 at 1.07-1.12).
    """

    max_events_per_step: int = setting(20_000, ge=0)
    search_per_roi_window: int = setting(64, ge=0)
    max_searched_per_step: int = setting(2500, ge=0)
    realtime: float = setting(0.0, ge=0)
    min_searched_per_step: int = setting(1000, ge=0)
    min_events_per_step: int = setting(2000, ge=0)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.realtime:
            return
        if not self.max_searched_per_step:
            raise FieldError(self, "realtime", "needs a search budget to adapt: set "
                             "'max_searched_per_step' > 0 (the highest budget)")
        if self.min_searched_per_step > self.max_searched_per_step:
            raise FieldError(self, "min_searched_per_step",
                             f"({self.min_searched_per_step}) must not exceed "
                             f"'max_searched_per_step' ({self.max_searched_per_step})")
        if self.max_events_per_step and self.min_events_per_step > self.max_events_per_step:
            raise FieldError(self, "min_events_per_step",
                             f"({self.min_events_per_step}) must not exceed "
                             f"'max_events_per_step' ({self.max_events_per_step}); 0 keeps "
                             "the load control from shedding events")


@dataclass
class RemeasureConfig(Config):
    """The velocity steps before the first pose (:mod:`evtrack.tracking.remeasure`).

    Attributes:
        before_pose: before the first pose (and after losing the object) run the flow and the
            velocity filter on all events, with the sensor depth's patch medians, so that the first
            pose, which arrives ``pose_latency_ms`` late, is carried to the present by the measured
            motion (``full`` and ``velocity``). Model depth needs a pose: with ``depth.source:
            model`` the flow runs but the velocity filter only predicts, and the steps wait for
            ``on_pose``.
        on_pose: with ``before_pose``, keep those steps' RoI flows and depth frames (model depth:
            rendered at the timeline's poses then; on the benchmark set, 4 kHz, oracle poses, this
            took ``depth.source: model`` from 11.82 cm / 25.15 deg to 6.44 / 16.63 on `faster` and
            from 3.04 / 8.22 to 2.70 / 6.49 on `regular`, 2026-11-27: without it the first pose, 200
            ms old, is held still and the track starts far off), and once the late pose has started
            the track, measure the steps since that pose again at the poses the filter then has
            (RoIs inside the silhouette, depths in its range, the object's centre as pivot) and
            carry the pose to the present with these twists. Without a pose, neither the object's
            depth range nor its centre is known: stale depth frames put many RoIs on the background
            and the motion about the camera's origin confounds translation with rotation. Measured
            again at a wrong pose, though, the steps lose their RoIs and take depths out of the
            object's range, which carries the wrong pose further off: see ``min_inside``.
        min_inside: the steps are measured again only when at least this fraction of the RoI flows
            (of at least 5 supporting events) of the 50 ms after the pose lie in the silhouette
            (with ``mask_margin_px``) at the timeline's pose of their step, else they keep their
            twists (counted in ``TrackerStats.remeasures_skipped``). Measured: 0.999-1.0 for oracle
            poses (1 cm, 1.7° per axis) on the eight YCB sequences and for the demo's network on
            seeds 0 and 2-5; 0.94 for its first pose of seed 1, 9.5 cm and 36° off.
    """

    before_pose: bool = True
    on_pose: bool = True
    min_inside: float = setting(0.98, ge=0, le=1)
